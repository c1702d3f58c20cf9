"""Command line: ``gslam run``, ``gslam bench`` and friends."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from gslam_jax import choices  # light (no JAX), as the next two
from gslam_jax.config import ConfigError  # light (no JAX), so --exact can still set XLA_FLAGS
from gslam_jax.errors import InputError
from gslam_jax.sim.courses import COURSES  # light (no JAX) too

__all__ = ["main"]


class ProgressBar:
    """A one-line console progress bar on stderr; when stderr is not a terminal (a log file, a
    pipe) only one final line is written."""

    def __init__(self, label: str, stream=None):
        self.label = label
        self.stream = sys.stderr if stream is None else stream
        isatty = getattr(self.stream, "isatty", None)
        self.tty = bool(isatty()) if callable(isatty) else False
        self.start = time.perf_counter()
        self.last = -1.0
        self.finished = False

    def __call__(self, done: int, total: int) -> None:
        now = time.perf_counter()
        if not self.tty:
            if done >= total and not self.finished:
                self.finished = True
                self.stream.write(f"{self.label}: {done}/{total} in {now - self.start:.1f}s\n")
                self.stream.flush()
            return
        if done < total and now - self.last < 0.2:
            return
        self.last = now
        frac = done / max(total, 1)
        bar = "#" * int(30 * frac)
        end = "\n" if done >= total else ""
        self.stream.write(f"\r{self.label} [{bar:<30}] {done}/{total} "
                          f"{now - self.start:6.1f}s{end}")
        self.stream.flush()


def _positive_int(text: str) -> int:
    """argparse type: an integer >= 1 (else a usage error)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def _seed(text: str) -> int:
    """argparse type: a seed 0 <= seed < 2^32 (else a usage error)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer seed, got {text!r}") from None
    if not 0 <= value < 2 ** 32:
        raise argparse.ArgumentTypeError(f"a seed must be in [0, 2^32), got {value}")
    return value


def _check_source_arguments(args: argparse.Namespace) -> None:
    """Reject source options that would be silently ignored (ConfigError naming them)."""
    if args.run_file is not None:
        extra = [opt for opt, given in (("--source", args.source != "sim"),
                                        ("--path", args.path is not None),
                                        ("--sequence", args.sequence is not None),
                                        ("--max-frames", args.max_frames is not None)) if given]
        if extra:
            raise ConfigError(f"{args.run_file}: a Run file is used as it is; {', '.join(extra)} "
                              "only apply without one (drop them, or re-create the Run with "
                              "--save-run)")
        return
    if args.path is not None and args.source not in ("kitti", "euroc"):
        raise ConfigError(f"--path is for --source kitti/euroc, not --source {args.source}")
    if args.sequence is not None and args.source != "kitti":
        raise ConfigError(f"--sequence is for --source kitti, not --source {args.source}")


def _load_source(args: argparse.Namespace, config, progress: Callable[[int, int], None]):
    """Return (Run, description) for the chosen source."""
    from gslam_jax.run import load_run
    from gslam_jax.slam import localmap_params

    params = localmap_params(config)
    if args.run_file is not None:
        return load_run(args.run_file), str(args.run_file), None
    if args.source == "sim":
        from gslam_jax.datasets.sim import simulate_run
        run, info = simulate_run(args.course, seed=args.seed, params=params,
                                 max_frames=args.max_frames, progress=progress)
        return run, f"simulated course {args.course} (seed {args.seed})", info
    if args.source == "sim-stereo":
        from gslam_jax.datasets.sim_stereo import load_sim_stereo
        run, info = load_sim_stereo(args.course, args.seed, params, max_frames=args.max_frames,
                                    progress=progress)
        print(info.text())
        return run, f"rendered stereo of course {args.course} (seed {args.seed})", None
    if args.source in ("kitti", "euroc") and args.path is None:
        raise ConfigError(f"--source {args.source} needs --path DATASET_FOLDER")
    if args.source == "kitti":
        from gslam_jax.datasets.kitti import KittiParams, find_sequence, kitti_frontend
        sequence = find_sequence(Path(args.path), args.sequence).name
        fe = kitti_frontend(args.path, KittiParams(  # KITTI's own front-end defaults, with:
            sequence=sequence, max_frames=args.max_frames,
            frontend=dataclasses.replace(KittiParams().frontend, local_map=params,
                                         on_bad_frame=args.on_bad_frame)))
        print(fe.summary.text())
        return fe.run, f"KITTI {args.path} sequence {sequence}", None
    if args.source == "euroc":
        from gslam_jax.datasets.euroc import EurocParams, euroc_frontend
        from gslam_jax.vo.frontend import FrontEndParams
        fe = euroc_frontend(args.path, EurocParams(
            max_frames=args.max_frames,
            frontend=FrontEndParams(local_map=params, on_bad_frame=args.on_bad_frame)))
        print(fe.summary.text())
        return fe.run, f"EuRoC {args.path}", None
    raise SystemExit(f"unknown source {args.source!r}")


def _load_config(args: argparse.Namespace):
    """--config (with the [course.<name>.*] tables of a Table I config applied for a simulated
    --course), then the --set overrides."""
    from gslam_jax.config import layered_config

    simulated = getattr(args, "run_file", None) is None and args.source in ("sim", "sim-stereo")
    return layered_config(args.config, args.course if simulated else None, args.set)


@contextlib.contextmanager
def _results_dir(out: Path | None, kind: str) -> Iterator[Path]:
    """Create the results directory before any work (ConfigError naming it when it cannot be);
    the folders created here are removed again if the command fails before writing into them."""
    path = Path(out) if out else Path("results") / time.strftime(f"{kind}-%Y%m%d-%H%M%S")
    name = f"--out {path}" if out else f"results directory {path}"
    if path.exists() and not path.is_dir():
        raise ConfigError(f"{name}: exists and is not a directory")
    new = [p for p in (path, *path.parents) if not p.exists()]  # deepest first
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ConfigError(f"{name}: cannot create the directory ({err})") from err
    try:
        yield path
    except BaseException:
        for folder in new:
            if not folder.is_dir() or any(folder.iterdir()):
                break
            folder.rmdir()
        raise


def _json_ready(value):
    """``value`` with NumPy scalars as Python numbers and NaN/inf as None (valid JSON)."""
    if isinstance(value, dict):
        return {k: _json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_ready(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _write_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(_json_ready(data), indent=2, allow_nan=False))


def cmd_run(args: argparse.Namespace) -> int:
    from gslam_jax import metrics, slam
    from gslam_jax.config import config_to_toml
    from gslam_jax.io import save_map, write_kitti, write_tum

    _check_source_arguments(args)
    config = _load_config(args)
    with _results_dir(args.out, "run") as out:
        gps_log = None  # a GPS file is read before the front-end: its errors come first
        if args.gps is not None and str(args.gps) != "sim":
            from gslam_jax import gps
            gps_log = gps.read_gps_log(args.gps)
        run, description, sim_info = _load_source(args, config, ProgressBar("front-end"))
        if args.save_run:
            from gslam_jax.run import save_run
            save_run(args.save_run, run)
        gps_input = None
        if args.gps is not None:
            from gslam_jax import georeference
            gps_input = georeference.gps_input(args.gps, run, args.seed, log=gps_log)
        print(f"source: {description}: {run.num_frames} frames, {run.num_local_maps} local maps, "
              f"{run.distance():.1f} m")
        result = slam.run_slam(run, config, progress=ProgressBar("gamma-slam"))
    (out / "config.toml").write_text(config_to_toml(config))
    if sim_info is not None:
        (out / "simulation.json").write_text(json.dumps(sim_info.summary(), indent=2, default=float))
    write_tum(out / "trajectory_tum.txt", run.timestamps, result.best_path)
    write_kitti(out / "trajectory_kitti.txt", result.best_path)
    write_tum(out / "vo_tum.txt", run.timestamps, result.vo_path)
    save_map(out / "map.npz", result.kmap, result.smap, result.map_origin, result.resolution)
    np.savez_compressed(out / "trace.npz", ess=result.ess, resampled=result.resampled,
                        updated=result.updated, log_lik=result.log_lik,
                        best_pose=result.best_pose, mean_pose=result.mean_pose)
    summary = {
        "source": description,
        "frames": run.num_frames,
        "local_maps": run.num_local_maps,
        "distance_m": run.distance(),
        "particles": config.filter.particles,
        "resampling_events": int(np.sum(result.resampled)),
        "extent_violations": result.extent_violations,
        "empty_observations": result.empty_observations,
        "vo_failures": int(np.sum(run.vo_failed)) if run.vo_failed is not None else 0,
        "filter_seconds": result.seconds,
        "compile_seconds": result.compile_seconds,
    }
    if run.ground_truth is not None:
        summary.update(metrics.errors_over_known_frames(
            {"vo": result.vo_path, "slam": result.best_path}, run.ground_truth))
    slam_std = _write_figures(out, run, result, config.filter.particles,
                              config.filter.resample_ratio)
    _write_json(out / "summary.json", summary)  # rewritten below with the GPS figures
    print(f"distance: {summary['distance_m']:.1f} m")
    if run.ground_truth is not None:
        scored = summary["gt_frames_scored"]
        over = "" if scored == run.num_frames else \
            f" (over the {scored} of {run.num_frames} frames with ground truth)"
        if "vo_rms_m" in summary:
            print(f"VO-only RMS: {summary['vo_rms_m']:.3f} m{over}")
            print(f"Gamma-SLAM RMS: {summary['slam_rms_m']:.3f} m{over}")
        else:
            print(f"ground truth: only {scored} of {run.num_frames} frames have a finite pose; "
                  "no RMS")
    print(f"resampling events: {summary['resampling_events']}, filter time "
          f"{result.seconds:.1f} s (+{result.compile_seconds:.1f} s first chunk incl. compile)")
    if result.extent_violations:
        print(f"WARNING: {result.extent_violations} particle updates reached the map edge")
    if result.empty_observations:
        print(f"note: {result.empty_observations} local maps had no informative cell (weights unchanged)")
    if gps_input is not None:
        summary["gps"] = georeference.write_gps_outputs(out, gps_input, run, result, slam_std)
        _write_json(out / "summary.json", summary)
    print(f"results: {out}")
    return 0


def _write_figures(out: Path, run, result, num_particles: int,
                   threshold: float = 0.5) -> np.ndarray:
    """Map PNGs (VO-only beside Gamma-SLAM, coloured by expected std) and the ESS plot with the
    resampling threshold (``threshold`` J, filter.resample_ratio); returns the Gamma-SLAM map's
    expected std."""
    from gslam_jax import cells, metrics, plots

    slam_std = np.asarray(cells.expected_std(result.kmap, result.smap))
    vo_map = metrics.vo_only_map(run)
    vo_std = np.asarray(cells.expected_std(vo_map.k, vo_map.S))
    plots.save_map_png(out / "map.png", slam_std, result.map_origin, result.resolution,
                       path=result.best_path, title="Gamma-SLAM")
    plots.save_map_comparison_png(out / "maps_vo_vs_slam.png", vo_std, vo_map.origin, slam_std,
                                  result.map_origin, result.resolution, vo_path=result.vo_path,
                                  slam_path=result.best_path)
    plots.save_ess_png(out / "ess.png", result.ess, num_particles, resampled=result.resampled,
                       threshold=threshold)
    return slam_std


def _config_and_run(args: argparse.Namespace):
    _check_source_arguments(args)
    config = _load_config(args)
    run, description, _ = _load_source(args, config, ProgressBar("front-end"))
    print(f"source: {description}: {run.num_frames} frames, {run.num_local_maps} local maps")
    return config, run


def _values_text(values: dict[str, float]) -> str:
    return ", ".join(f"{k} = {v:.5g}" for k, v in values.items())


def cmd_search(args: argparse.Namespace) -> int:
    from gslam_jax.config import config_to_toml
    from gslam_jax.search import SearchError, config_with_values, load_space, search

    try:
        space, options = load_space(args.space)
        with _results_dir(args.out, "search") as out:
            config, run = _config_and_run(args)
            result = search(run, config, space,
                            design=args.design or options.get("design", "halton"),
                            n=args.n if args.n is not None else options.get("n", 64),
                            objective=args.objective or options.get("objective", "rms"),
                            path=args.score_path or options.get("path", "mean"),
                            seed=options.get("seed", 0), batch=args.batch,
                            progress=ProgressBar("search"))
            best = result.best()
            best_config = config_with_values(config, best)
    except SearchError as err:
        raise ConfigError(str(err)) from err
    result.to_csv(out / "results.csv")
    result.to_json(out / "results.json")
    (out / "best.toml").write_text(config_to_toml(best_config))
    unit = " m" if result.objective_name == "rms" else ""
    print(f"best: {result.objective_name} = {result.objective[0]:.5g}{unit} at "
          f"{_values_text(best)}")
    print(f"results: {out} (best.toml: the config with the best values, for --config)")
    return 0


def cmd_tune(args: argparse.Namespace) -> int:
    from gslam_jax.config import config_to_toml
    from gslam_jax.search import SearchError, config_with_values
    from gslam_jax.tuning import TuneError, tune

    every = max(1, args.steps // 10)

    def on_step(step: int, loss: float, values: dict[str, float]) -> None:
        if step % every == 0 or step == 1 or step == args.steps:
            print(f"step {step}/{args.steps}: loss {loss:.6g} (at the step's start), then "
                  f"{_values_text(values)}", flush=True)

    try:
        names = args.params.split(",") if args.params else None
        with _results_dir(args.out, "tune") as out:
            config, run = _config_and_run(args)
            result = tune(run, config, objective=args.objective, optimizer=args.optimizer,
                          lr=args.lr, steps=args.steps, names=names,
                          runs_per_step=args.runs_per_step, crn=args.crn, on_step=on_step)
            tuned_config = config_with_values(config, result.values)
    except (TuneError, SearchError) as err:
        raise ConfigError(str(err)) from err
    print("tuned: " + _values_text(result.values))
    (out / "tuned.toml").write_text(config_to_toml(tuned_config))
    (out / "tuned.json").write_text(json.dumps({
        "objective": result.objective, "values": result.values,
        "history": np.asarray(result.history).tolist(),
        "losses": np.asarray(result.losses).tolist(), "seconds": result.seconds}, indent=2))
    print(f"results: {out} (tuned.toml: the config with the tuned values, for --config)")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from gslam_jax.bench import main as bench_main
    return bench_main(args.particles, args.local, args.map, args.repeats, args.mode, args.json,
                      course=args.course, course_particles=args.course_particles,
                      plot_path=args.plot, particle_block=args.particle_block)


def cmd_table1(args: argparse.Namespace) -> int:
    from gslam_jax.table1 import main as table1_main
    return table1_main(args.courses, args.seeds, args.particles, args.config, args.json, args.quick)


def cmd_compare(args: argparse.Namespace) -> int:
    if args.exact:
        import os
        if "jax" in sys.modules:
            raise SystemExit("--exact must be set before JAX is imported")
        # No fused multiply-adds in XLA, so float32 rounding matches NumPy's step for step.
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_max_isa=AVX").strip()
    from gslam_jax.run import load_run
    from gslam_jax.config import load_table_config
    from gslam_jax.tiled.compare import compare

    # A Table I config works too: its shared settings are used, its [course.*] tables are not.
    config, per_course = load_table_config(args.config)
    if per_course:
        print(f"note: {args.config}: compare uses the shared settings; the [course.<name>.*] "
              f"tables ({', '.join(per_course)}) are not applied")
    run = load_run(args.run_file) if args.run_file else None
    result = compare(run, config, particles=args.particles,
                     unknown_cells=args.unknown_cells, tile_size=args.tile_size, seed=args.seed,
                     out_dir=args.out)
    return 0 if result.get("agreement", {}).get("ok", True) else 1


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="gslam", description="Gamma-SLAM in JAX "
                                     "(Marks et al., Journal of Field Robotics 2009)")
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
    p.add_argument("--out", type=Path, help="results directory, created before the run "
                   "(default results/run-<time>)")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("search", help="batched parameter search (vmapped/sharded over sets)")
    _add_source_arguments(p)
    p.add_argument("--space", type=Path, required=True, help="TOML search space (see "
                   "configs/search_example.toml)")
    p.add_argument("--design", choices=choices.SEARCH_DESIGNS)
    p.add_argument("--n", type=_positive_int, help="number of parameter sets")
    p.add_argument("--objective", choices=choices.SEARCH_OBJECTIVES)
    p.add_argument("--score-path", choices=choices.SCORE_PATHS,
                   help="path scored by rms: weighted mean or final best particle")
    p.add_argument("--batch", type=int, help="parameter sets per chunk")
    p.add_argument("--out", type=Path, help="write results.csv, results.json and best.toml here "
                   "(default results/search-<time>)")
    p.set_defaults(func=cmd_search)

    p = sub.add_parser("tune", help="gradient tuning of the noise parameters with optax")
    _add_source_arguments(p)
    p.add_argument("--objective", choices=choices.TUNE_OBJECTIVES, default="loglik")
    p.add_argument("--optimizer", default="adam", help="an optax optimiser by name whose "
                   "update needs only the gradient (adam, sgd, ...; lbfgs is refused)")
    p.add_argument("--lr", type=float, default=0.05)
    p.add_argument("--steps", type=_positive_int, default=100)
    p.add_argument("--params", help="comma-separated names (default: the objective's)")
    p.add_argument("--runs-per-step", type=int, default=4)
    p.add_argument("--crn", action="store_true", help="common random numbers across steps")
    p.add_argument("--out", type=Path, help="write tuned.toml (a config for --config) and "
                   "tuned.json here (default results/tune-<time>)")
    p.set_defaults(func=cmd_tune)
    _build_rest(sub)
    return parser


def _add_source_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_file", nargs="?", type=Path, help="native .npz Run file (see README)")
    p.add_argument("--source", choices=choices.SOURCES, default="sim",
                   help="where frames come from when no Run file is given (default: sim)")
    p.add_argument("--course", default="mars-yard-a", choices=COURSES, metavar="COURSE",
                   help=f"simulated course: {', '.join(COURSES)} (default mars-yard-a)")
    p.add_argument("--path", type=Path, help="dataset folder for --source kitti/euroc")
    p.add_argument("--sequence", metavar="NN", help="KITTI sequence: the folder under "
                   "PATH/sequences (e.g. 00); needed when there are several")
    p.add_argument("--seed", type=_seed, default=0, help="simulation seed (0 <= seed < 2^32)")
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
    p.add_argument("--particle-block", type=int, nargs="+", default=[0],
                   help="particles per pass of the update (0: automatic); several values "
                   "compare block sizes in one process")
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser("table1", help="the paper's Table I on the five simulated courses")
    p.add_argument("--courses", nargs="+", default=list(COURSES), choices=COURSES, metavar="COURSE")
    p.add_argument("--seeds", type=_seed, nargs="+", default=[0, 1, 2])
    p.add_argument("--particles", type=_positive_int, metavar="J",
                   help="particles (default: the config's filter.particles, per course; 200 if "
                   "the config does not set it)")
    p.add_argument("--config", type=Path, help="TOML config, may hold [course.<name>.*] tables")
    p.add_argument("--json", type=Path)
    p.add_argument("--quick", action="store_true", help="Mars Yard A, one seed, J <= 100")
    p.set_defaults(func=cmd_table1)

    p = sub.add_parser("compare", help="dense JAX filter vs the tiled copy-on-write reference")
    p.add_argument("run_file", nargs="?", type=Path, help="Run file (default: a simulated course)")
    p.add_argument("--config", type=Path, help="TOML config (a Table I config's [course.*] tables "
                   "are not applied)")
    p.add_argument("--particles", type=_positive_int, default=200)
    p.add_argument("--unknown-cells", choices=choices.UNKNOWN_CELLS)
    p.add_argument("--tile-size", type=float, help="tile side, metres (default 10)")
    p.add_argument("--seed", type=_seed, default=0)
    p.add_argument("--out", type=Path, help="write compare.json and compare_fig4.png here")
    p.add_argument("--exact", action="store_true",
                   help="disable XLA's fused multiply-adds so both filters round identically")
    p.set_defaults(func=cmd_compare)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (InputError, FileNotFoundError) as err:
        print(f"gslam: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
