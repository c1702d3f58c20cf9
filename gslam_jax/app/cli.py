"""Command line: ``gslam run``, ``gslam bench`` and friends."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from gslam_jax import choices  # light (no JAX), as the next two
from gslam_jax.config import ConfigError  # light (no JAX), so --exact can still set XLA_FLAGS
from gslam_jax.errors import InputError
from gslam_jax.app.outputs import json_ready  # light too
from gslam_jax.app.progress import ProgressBar
from gslam_jax.app import info, merge, view
from gslam_jax.app.results import results_folder, writing
from gslam_jax.datasets.registry import Source, get_source, source_names
from gslam_jax.sim.courses import COURSES  # light (no JAX) too

if TYPE_CHECKING:
    from gslam_jax.tuning.motion_fit import MotionFit

__all__ = ["main", "console"]


def _integer(text: str, low: int, high: int | None, what: str, bounds: str) -> int:
    """An integer in [low, high) from ``text``, else a usage error saying ``what`` was expected
    (a non-number) or ``bounds`` (one out of range)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if value < low or (high is not None and value >= high):
        raise argparse.ArgumentTypeError(f"{bounds}, got {value}")
    return value


def _positive_int(text: str) -> int:
    """argparse type: an integer >= 1 (else a usage error)."""
    return _integer(text, 1, None, "a positive integer", "expected a positive integer")


def _nonnegative_int(text: str) -> int:
    """argparse type: an integer >= 0 (else a usage error); 0 means automatic."""
    return _integer(text, 0, None, "an integer >= 0", "expected an integer >= 0 (0: automatic)")


def _seed(text: str) -> int:
    """argparse type: a seed 0 <= seed < 2^32 (else a usage error)."""
    return _integer(text, 0, 2 ** 32, "an integer seed", "a seed must be in [0, 2^32)")


def _topic(text: str) -> tuple[str, str]:
    """argparse type: ROLE=NAME (NAME may be empty: none) for --topic."""
    role, eq, name = text.partition("=")
    if not eq or not role.strip():
        raise argparse.ArgumentTypeError(f"expected ROLE=NAME (e.g. left=/cam0/image_raw), "
                                         f"got {text!r}")
    return role.strip(), name.strip()


def _positive_float(text: str) -> float:
    """argparse type: a finite number > 0 (else a usage error; float() accepts 'nan', 'inf')."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a finite positive number, got {text}")
    return value


def _triple(text: str, nonnegative: bool) -> tuple[float, float, float]:
    """Three finite comma-separated numbers (>= 0 with ``nonnegative``), else a usage error."""
    parts = text.split(",")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    what = "three numbers >= 0" if nonnegative else "three numbers"
    if len(values) != 3 or not all(math.isfinite(v) and (v >= 0 or not nonnegative)
                                   for v in values):
        raise argparse.ArgumentTypeError(f"expected {what} separated by commas, got {text!r}")
    return values  # type: ignore[return-value]


def _pose(text: str) -> tuple[float, float, float]:
    """argparse type: X,Y,THETA (metres, radians)."""
    return _triple(text, nonnegative=False)


def _pose_sigma(text: str) -> tuple[float, float, float]:
    """argparse type: SX,SY,STHETA standard deviations >= 0 (metres, radians)."""
    return _triple(text, nonnegative=True)


class _Given(argparse.Action):
    """Store the value and note that the option was given (``<dest>_given``), not defaulted."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        setattr(namespace, self.dest, values)
        setattr(namespace, f"{self.dest}_given", True)


def _use_course_path(args: argparse.Namespace) -> None:
    """``--course-path FILE`` is ``--source sim-path --path FILE``: set those, or a ConfigError
    for a Run file, another --source or a --path beside it."""
    what = f"--course-path {args.course_path}"
    if args.run_file is not None:
        raise ConfigError(f"{args.run_file}: a Run file is used as it is; {what} drives a "
                          "simulated world along a trajectory instead: give one of them")
    if getattr(args, "source_given", False) and args.source != "sim-path":
        raise ConfigError(f"{what} is --source sim-path --path FILE; it cannot be used with "
                          f"--source {args.source}")
    if args.path is not None:
        raise ConfigError(f"{what} and --path {args.path}: {what} is --source sim-path "
                          "--path FILE; name the trajectory once")
    args.source, args.path = "sim-path", args.course_path


def _source(args: argparse.Namespace) -> Source:
    """The source request from the source arguments."""
    return Source(run_file=args.run_file, source=args.source, course=args.course,
                  path=args.path, sequence=args.sequence, seed=args.seed,
                  max_frames=args.max_frames, on_bad_frame=args.on_bad_frame,
                  noise_seed=args.noise_seed, topics=tuple(args.topic or ()))


def _load_config(args: argparse.Namespace):
    """--config (with the [course.<name>.*] tables of a Table I config applied for a simulated
    --course), then the --set overrides."""
    from gslam_jax.config import layered_config

    simulated = getattr(args, "run_file", None) is None and get_source(args.source).simulated
    return layered_config(args.config, args.course if simulated else None, args.set)


def cmd_run(args: argparse.Namespace) -> int:
    from gslam_jax.app.pipeline import load_prior, run_pipeline

    config = _load_config(args)
    prior = None
    if args.prior_map is not None:
        prior = load_prior(args.prior_map, args.start, args.start_sigma, config)
    elif args.start is not None or args.start_sigma is not None:
        raise ConfigError("--start and --start-sigma place the run in a prior map: give "
                          "--prior-map RUN_A too")
    with view.RunWatch.open(args.viewer, args.viewer_save, args.viewer_every) as watch:
        out, _ = run_pipeline(_source(args), config, args.out, overwrite=args.overwrite,
                              gps=args.gps, save_run=args.save_run, progress=ProgressBar,
                              prior=prior, on_chunk=watch.on_chunk, chunk=watch.chunk,
                              map_check=not args.no_map_check)
        watch.finish(out)
    print(f"results: {out}")
    return 0


def _config_and_run(args: argparse.Namespace):
    """The config and the Run of a command's source arguments: the same checks and loading
    as ``gslam run`` (``pipeline.check_inputs``, ``pipeline.prepare_source``)."""
    from gslam_jax.app.pipeline import check_inputs, prepare_source

    config = _load_config(args)
    src = _source(args)
    check_inputs(src, config)
    return config, prepare_source(src, config, ProgressBar("front-end")).run


def _values_text(values: dict[str, float]) -> str:
    return ", ".join(f"{k} = {v:.5g}" for k, v in values.items())


def cmd_search(args: argparse.Namespace) -> int:
    from gslam_jax.config import config_to_toml
    from gslam_jax.tuning.search import search
    from gslam_jax.tuning.space import SearchError, config_with_values, load_space

    try:
        space, options = load_space(args.space)
        with results_folder(args.out, "search", overwrite=args.overwrite,
                            command="gslam search") as folder:
            config, run = _config_and_run(args)
            result = search(run, config, space,
                            design=args.design or options.get("design", "halton"),
                            n=args.n if args.n is not None else options.get("n", 64),
                            objective=args.objective or options.get("objective", "rms"),
                            path=args.score_path or options.get("path", config.filter.estimate),
                            seed=options.get("seed", 0), batch=args.batch,
                            progress=ProgressBar("search"))
            best = result.best()
            best_config = config_with_values(config, best)
            with writing(folder):
                result.to_csv(folder.staging / "results.csv")
                result.to_json(folder.staging / "results.json")
                (folder.staging / "best.toml").write_text(config_to_toml(best_config))
    except SearchError as err:
        raise ConfigError(str(err)) from err
    unit = " m" if result.objective_name == "rms" else ""
    print(f"best: {result.objective_name} = {result.objective[0]:.5g}{unit} at "
          f"{_values_text(best)}")
    print(f"results: {folder.target} (best.toml: the config with the best values, for --config)")
    return 0


def cmd_tune(args: argparse.Namespace) -> int:
    from gslam_jax.config import config_to_toml
    from gslam_jax.tuning.space import SearchError, config_with_values
    from gslam_jax.tuning.gradient import TuneError, tune

    every = max(1, args.steps // 10)

    def on_step(step: int, loss: float, values: dict[str, float]) -> None:
        if step % every == 0 or step == 1 or step == args.steps:
            print(f"step {step}/{args.steps}: loss {loss:.6g} (at the step's start), then "
                  f"{_values_text(values)}", flush=True)

    try:
        names = args.params.split(",") if args.params else None
        with results_folder(args.out, "tune", overwrite=args.overwrite,
                            command="gslam tune") as folder:
            config, run = _config_and_run(args)
            result = tune(run, config, objective=args.objective, optimizer=args.optimizer,
                          lr=args.lr, steps=args.steps, names=names,
                          runs_per_step=args.runs_per_step, crn=args.crn, on_step=on_step)
            tuned_config = config_with_values(config, result.values)
            with writing(folder):
                (folder.staging / "tuned.toml").write_text(config_to_toml(tuned_config))
                (folder.staging / "tuned.json").write_text(json.dumps(json_ready({
                    "objective": result.objective, "values": result.values,
                    "history": np.asarray(result.history).tolist(),
                    "losses": np.asarray(result.losses).tolist(),
                    "seconds": result.seconds}), indent=2, allow_nan=False))
    except (TuneError, SearchError) as err:
        raise ConfigError(str(err)) from err
    print("tuned: " + _values_text(result.values))
    print(f"results: {folder.target} (tuned.toml: the config with the tuned values, for --config)")
    return 0


def _fit_text(fit: MotionFit, frames: int) -> str:
    """The error figures behind a motion fit, in mm and mrad."""
    text = (f"frames used: {fit.frames} of {frames}, errors summed over windows of {fit.window} "
            f"frame{'s' if fit.window > 1 else ''}\n"
            f"VO errors: along-track RMS {fit.along_rms * 1e3:.3g} mm, across-track RMS "
            f"{fit.across_rms * 1e3:.3g} mm, heading RMS {fit.heading_rms * 1e3:.3g} mrad "
            f"(median |d| {fit.median_dist:.3g} m, |dtheta| {fit.median_turn * 1e3:.3g} mrad)")
    if fit.alpha_theta_at_bound:
        text += "\nnote: alpha_theta stopped at its bound: the turns do not determine it"
    return text


def _evidence_fit(run, config, args: argparse.Namespace):
    """``fit-motion --evidence``: the config with its alphas scaled by the evidence ladder's
    best factor (``tuning.evidence_fit``), and the ladder as text."""
    from gslam_jax.tuning.evidence_fit import (DEFAULT_FACTORS, DEFAULT_SEEDS, MIN_GAIN,
                                               fit_noise_scale)

    factors = args.factors or DEFAULT_FACTORS
    seeds = args.evidence_seeds or DEFAULT_SEEDS

    def progress(done: int, total: int) -> None:
        print(f"  seed {done} of {total} done", file=sys.stderr, flush=True)

    print(f"log evidence of {len(factors)} noise factors x {len(seeds)} filter seed(s), fixed "
          "tempering ...", file=sys.stderr, flush=True)
    fit = fit_noise_scale(run, config, factors, seeds, progress)
    rows = "\n".join(f"  x{f:<9g} {e:12.2f}{'  <- chosen' if f == fit.factor else ''}"
                     for f, e in zip(fit.factors, fit.log_evidence))
    text = (f"log evidence (fixed tempering, mean over filter seeds "
            f"{', '.join(map(str, seeds))}) of the config's alphas times:\n{rows}")
    if fit.kept:
        text += (f"\nkept the given alphas: no factor's evidence is more than {MIN_GAIN:g} "
                 "above theirs")
    if not all(math.isfinite(e) for e in fit.log_evidence):
        text += ("\nnan: with that noise some particle observed cells beyond the map's edge "
                 "(its evidence would not be the whole log's; [map] margin widens the map)")
    if fit.on_edge:
        text += ("\nnote: the chosen factor is the ladder's edge: the noise may lie beyond it "
                 "(extend --factors)")
    if run.sensor == "stereo":
        text += ("\nnote: stereo local maps: their cells share disparity errors, the fixed-beta "
                 "likelihood is overconfident, and on three stereo logs the fitted noise did "
                 "worse than the defaults (narrower on KITTI, wider on rendered stereo; "
                 "docs/real-data.md). The evidence fit is for the point sensor")
    return fit.config(config), text


def cmd_fit_motion(args: argparse.Namespace) -> int:
    from gslam_jax.app.outfile import check_output_file, write_text_atomic
    from gslam_jax.config import MotionSection, config_to_toml, section_to_toml
    from gslam_jax.tuning.motion_fit import fit_run

    if args.out is not None:  # a folder, a read-only place: refused before the fit
        check_output_file(args.out, "--out")
        if args.out.exists() and not args.overwrite:
            raise ConfigError(f"--out {args.out}: exists (--overwrite replaces it)")
    if not args.evidence and (args.factors or args.evidence_seeds):
        raise ConfigError("--factors and --evidence-seeds go with --evidence")
    if args.evidence and args.window is not None:
        raise ConfigError("--window is the fit to the ground truth's; --evidence has none")
    config, run = _config_and_run(args)
    if args.evidence:
        fitted, text = _evidence_fit(run, config, args)
    else:
        fit = fit_run(run, args.window)
        fitted = dataclasses.replace(config, motion=MotionSection(
            alpha_d=fit.alpha_d, alpha_theta_d=fit.alpha_theta_d, alpha_theta=fit.alpha_theta,
            alpha_cross=fit.alpha_cross))
        text = _fit_text(fit, run.num_frames)
    print(section_to_toml(fitted, "motion"))
    print(text)
    if args.out is not None:
        write_text_atomic(args.out, config_to_toml(fitted), "--out")
        print(f"config: {args.out} (the config with the fitted [motion], for --config)")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from gslam_jax.app.bench import main as bench_main
    return bench_main(args.particles, args.local, args.map, args.repeats, args.mode, args.json,
                      course=args.course, course_particles=args.course_particles,
                      plot_path=args.plot, particle_block=args.particle_block,
                      stores=args.store)


def cmd_table1(args: argparse.Namespace) -> int:
    from gslam_jax.app.table1 import main as table1_main
    return table1_main(args.courses, args.seeds, args.particles, args.config, args.json, args.quick,
                       args.set or [])


def cmd_compare(args: argparse.Namespace) -> int:
    if args.exact:
        import os
        if "jax" in sys.modules:
            raise SystemExit("--exact must be set before JAX is imported")
        # No fused multiply-adds in XLA, so float32 rounding matches NumPy's step for step.
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_max_isa=AVX").strip()
    from gslam_jax.run import load_run
    from gslam_jax.config import load_table_config
    from gslam_jax.app.compare import compare

    # A Table I config works too: its shared settings are used, its [course.*] tables are not.
    config, per_course = load_table_config(args.config)
    if per_course:
        print(f"note: {args.config}: compare uses the shared settings; the [course.<name>.*] "
              f"tables ({', '.join(per_course)}) are not applied")
    run = load_run(args.run_file) if args.run_file else None
    result = compare(run, config, particles=args.particles,
                     unknown_cells=args.unknown_cells, tile_size=args.tile_size, seed=args.seed,
                     out_dir=args.out, store=args.store, pool_tiles=args.pool_tiles,
                     overwrite=args.overwrite)
    return 0 if result.get("agreement", {}).get("ok", True) else 1


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="gslam", description="Gamma-SLAM in JAX "
                                     "(Marks et al., Journal of Field Robotics 2009)")
    info.add_version(parser)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("run", help="run Gamma-SLAM on a Run file, a simulated course or a dataset")
    _add_source_arguments(p)
    p.add_argument("--gps", help="GPS log (time, lat, lon, epe) to align the result to, read and "
                   "checked before the run; times are seconds on the run's clock (Run.timestamps: "
                   "EuRoC runs start at 0 at the first image, KITTI runs use times.txt). Readings "
                   "outside the run's time span are not used: at least 2 must fall inside it, "
                   "with a warning when fewer than half do. Or 'sim' for a simulated WAAS-like "
                   "receiver on a run with ground truth")
    p.add_argument("--save-run", type=Path, help="also write the Run (after the front-end) as .npz")
    p.add_argument("--prior-map", type=Path, metavar="RUN_A", help="map reuse: start every "
                   "particle with this map (a gslam run results folder or its map.npz, same "
                   "[map] resolution), localise in it and extend it; the results are in its frame")
    p.add_argument("--start", type=_pose, metavar="X,Y,THETA", help="with --prior-map: the "
                   "run's start pose in the prior map's frame (metres, radians)")
    p.add_argument("--start-sigma", type=_pose_sigma, metavar="SX,SY,STHETA", help="with "
                   "--prior-map: standard deviations of the start pose (metres, radians); the "
                   "particles start spread by them (default 0,0,0: all at --start)")
    p.add_argument("--no-map-check", action="store_true", help="skip checking the finished map "
                   "against itself (consistency: each revisited stretch of the path "
                   "scored against the map built before it; terrain mapped twice is reported and "
                   "recorded in summary.json's map_consistency, and gslam merge refuses it)")
    p.add_argument("--out", type=Path, help="results directory (default results/run-<time>); "
                   "the results appear there only when complete (marker file COMPLETE); an "
                   "existing, non-empty folder is refused unless --overwrite")
    p.add_argument("--overwrite", action="store_true", help="replace an existing results "
                   "folder --out as a whole once the new results are complete")
    view.add_run_arguments(p, _positive_int)
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("search", help="batched parameter search (vmapped/sharded over sets)")
    _add_source_arguments(p)
    p.add_argument("--space", type=Path, required=True, help="TOML search space (see "
                   "configs/search_example.toml)")
    p.add_argument("--design", choices=choices.SEARCH_DESIGNS)
    p.add_argument("--n", type=_positive_int, help="number of parameter sets")
    p.add_argument("--objective", choices=choices.SEARCH_OBJECTIVES)
    p.add_argument("--score-path", choices=choices.SCORE_PATHS,
                   help="path scored by rms: final best particle or weighted mean "
                   "(default: [filter] estimate)")
    p.add_argument("--batch", type=_positive_int, help="parameter sets per chunk")
    p.add_argument("--out", type=Path, help="write results.csv, results.json and best.toml here "
                   "when complete (default results/search-<time>)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out folder")
    p.set_defaults(func=cmd_search)

    p = sub.add_parser("tune", help="gradient tuning of the noise parameters with optax")
    _add_source_arguments(p)
    p.add_argument("--objective", choices=choices.TUNE_OBJECTIVES, default="loglik")
    p.add_argument("--optimizer", default="adam", help="an optax optimiser by name whose "
                   "update needs only the gradient (adam, sgd, ...; lbfgs is refused)")
    p.add_argument("--lr", type=_positive_float, default=0.05, help="learning rate (> 0)")
    p.add_argument("--steps", type=_positive_int, default=100)
    p.add_argument("--params", help="comma-separated names (default: the objective's)")
    p.add_argument("--runs-per-step", type=_positive_int, default=4)
    p.add_argument("--crn", action="store_true", help="common random numbers across steps")
    p.add_argument("--out", type=Path, help="write tuned.toml (a config for --config) and "
                   "tuned.json here when complete (default results/tune-<time>)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out folder")
    p.set_defaults(func=cmd_tune)

    p = sub.add_parser("fit-motion", help="fit the [motion] alphas to the VO errors of a log "
                       "with ground truth (maximum likelihood of eqs. 2-3), or without it to "
                       "the filter's evidence (--evidence)")
    _add_source_arguments(p)
    p.add_argument("--window", type=_positive_int, help="fit the errors summed over this many "
                   "consecutive frames (default: the frames between two local maps, so that "
                   "correlated VO errors are fitted at the spread the filter's updates see)")
    p.add_argument("--evidence", action="store_true", help="no ground truth: scale the "
                   "config's alphas together by the factor with the highest log evidence of "
                   "the filter (fixed tempering; gslam_jax/tuning/evidence_fit.py)")
    p.add_argument("--factors", type=_positive_float, nargs="+", help="--evidence: the factors "
                   "tried (default: 1/64, 1/32, ..., 16)")
    p.add_argument("--evidence-seeds", type=int, nargs="+", metavar="SEED",
                   help="--evidence: filter seeds the log evidence is averaged over "
                   "(default 0 1 2)")
    p.add_argument("--out", type=Path, help="write the config with the fitted [motion] here "
                   "(TOML, for --config)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    p.set_defaults(func=cmd_fit_motion)
    _build_rest(sub)
    info.add_parser(sub)
    info.add_examples(sub)
    return parser


def _add_source_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_file", nargs="?", type=Path, help="native .npz Run file (docs/formats.md)")
    names = source_names()
    p.add_argument("--source", choices=names, default=Source.source, action=_Given,
                   help="where frames come from when no Run file is given: "
                   + "; ".join(f"{n}: {get_source(n).help}" for n in names)
                   + f" (default: {Source.source})")
    p.add_argument("--course", default="mars-yard-a", choices=COURSES, metavar="COURSE",
                   help=f"simulated course: {', '.join(COURSES)} (default mars-yard-a)")
    p.add_argument("--path", type=Path, help="the dataset of the source: " + "; ".join(
        f"--source {n}: {get_source(n).path}" for n in names if get_source(n).path))
    p.add_argument("--course-path", type=Path, metavar="FILE", help="drive a simulated world "
                   "along this trajectory (TUM or KITTI poses): the same as --source sim-path "
                   "--path FILE (--course picks the world kind and VO noise)")
    p.add_argument("--sequence", metavar="NN", help="the sequence to read (--source "
                   + "/".join(n for n in names if get_source(n).sequence)
                   + "), e.g. 00; needed when the dataset holds several")
    p.add_argument("--seed", type=_seed, help="simulation seed, 0 <= seed < 2^32 (default 0); "
                   "only for simulated sources and --gps sim (the filter's seed is filter.seed)")
    p.add_argument("--noise-seed", type=_seed, help="draw the VO and sensor noise from this seed "
                   "while the world and path stay those of --seed: the same terrain driven "
                   "again (--source sim; default: --seed)")
    p.add_argument("--topic", action="append", type=_topic, metavar="ROLE=NAME",
                   help="the bag topic of a role (--source "
                   + "/".join(n for n in names if get_source(n).topics)
                   + "; repeatable): left, right, left_info, right_info, wheel, imu, "
                   "ground_truth; ROLE= for none (optional roles); default: picked when one "
                   "topic fits (docs/formats.md)")
    p.add_argument("--max-frames", type=_positive_int, metavar="N",
                   help="use only the first N frames of the source (not with a Run file)")
    p.add_argument("--on-bad-frame", choices=choices.BAD_FRAME_POLICIES, default="error",
                   help="a missing/corrupt image stops the run (error) or is counted and bridged "
                   "by the fallback odometry")
    p.add_argument("--config", type=Path, help="TOML config (defaults: the paper's settings)")
    p.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE",
                   help="override one config value (repeatable)")


def _build_rest(sub) -> None:
    """bench, table1 and compare: commands with their own arguments."""
    p = sub.add_parser("bench", help="microseconds per particle per local-map update")
    p.add_argument("--particles", type=_positive_int, nargs="+", default=[50, 200, 1000])
    p.add_argument("--local", type=_positive_int, nargs="+", default=[64],
                   help="local map sides, cells")
    p.add_argument("--map", type=_positive_int, nargs="+", default=[640],
                   help="global map sides, cells")
    p.add_argument("--repeats", type=_positive_int, default=10)
    p.add_argument("--mode", choices=choices.UNKNOWN_CELLS, nargs="+",
                   default=list(choices.UNKNOWN_CELLS))
    p.add_argument("--json", type=Path, help="also write the figures as JSON")
    p.add_argument("--plot", type=Path, help="also plot us per particle against J (PNG)")
    p.add_argument("--course", choices=COURSES, metavar="COURSE",
                   help="also time a whole simulated course after compilation "
                   "(e.g. mars-yard-a), default settings")
    p.add_argument("--course-particles", type=_positive_int, default=200)
    p.add_argument("--particle-block", type=_nonnegative_int, nargs="+", default=[0],
                   help="particles per pass of the update (0: automatic); several values "
                   "compare block sizes in one process")
    p.add_argument("--store", choices=[s for s in choices.MAP_STORES if s != "auto"], nargs="+",
                   default=["dense"], help="map stores to time ([map] store; several: side by "
                   "side in one process)")
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser("table1", help="the paper's Table I on the five simulated courses")
    p.add_argument("--courses", nargs="+", default=list(COURSES), choices=COURSES, metavar="COURSE")
    p.add_argument("--seeds", type=_seed, nargs="+", default=[0, 1, 2])
    p.add_argument("--particles", type=_positive_int, metavar="J",
                   help="particles (default: the config's filter.particles, per course; 200 if "
                   "the config does not set it)")
    p.add_argument("--config", type=Path, help="TOML config, may hold [course.<name>.*] tables")
    p.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE",
                   help="override one config value on every course, after the config's course "
                   "tables (repeatable)")
    p.add_argument("--json", type=Path)
    p.add_argument("--quick", action="store_true", help="Mars Yard A, one seed, J <= 100")
    p.set_defaults(func=cmd_table1)

    merge.add_parser(sub)
    view.add_parser(sub)

    p = sub.add_parser("compare", help="dense JAX filter vs the tiled copy-on-write reference")
    p.add_argument("run_file", nargs="?", type=Path, help="Run file (default: a simulated course)")
    p.add_argument("--config", type=Path, help="TOML config (a Table I config's [course.*] tables "
                   "are not applied)")
    p.add_argument("--particles", type=_positive_int, default=200)
    p.add_argument("--unknown-cells", choices=choices.UNKNOWN_CELLS)
    p.add_argument("--tile-size", type=_positive_float, help="tile side, metres (default 10)")
    p.add_argument("--seed", type=_seed, default=0)
    p.add_argument("--out", type=Path, help="write compare.json and compare_fig4.png into "
                   "this results folder when complete; an existing, non-empty folder is "
                   "refused unless --overwrite")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out folder")
    p.add_argument("--exact", action="store_true",
                   help="disable XLA's fused multiply-adds so both filters round identically")
    p.add_argument("--store", choices=choices.MAP_STORES,
                   help="the JAX filter's map store (default: the config's [map] store)")
    p.add_argument("--pool-tiles", type=_nonnegative_int, help="shared store pool size "
                   "(default: the config's [map] pool_tiles; 0: automatic)")
    p.set_defaults(func=cmd_compare)


def _out_of_memory(err: BaseException) -> bool:
    """XLA's RESOURCE_EXHAUSTED (an allocation the process may not make) or a MemoryError."""
    return isinstance(err, MemoryError) or "RESOURCE_EXHAUSTED" in str(err)[:2000]


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if getattr(args, "course_path", None) is not None:
            _use_course_path(args)
        return args.func(args)
    except (InputError, FileNotFoundError) as err:
        print(f"gslam: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("gslam: interrupted; no results were written", file=sys.stderr)
        return 130
    except Exception as err:  # noqa: BLE001 - only memory exhaustion is reported, not hidden
        if not _out_of_memory(err):
            raise
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        print(f"gslam: error: out of memory ({first[:300]}); the process may use less memory "
              "than the machine has (a ulimit -v or container limit: check `ulimit -a`): use "
              "fewer [filter] particles, a coarser [map] resolution or a smaller [map] margin",
              file=sys.stderr)
        return 3


def console() -> None:
    """The ``gslam`` script: ``main``, then exit. After Ctrl-C the process ends without
    Python's teardown, which can crash (SIGSEGV) while XLA threads are still compiling."""
    code = main()
    if code == 130:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(130)
    sys.exit(code)


if __name__ == "__main__":
    console()
