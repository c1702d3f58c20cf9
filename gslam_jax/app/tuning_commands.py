"""``gslam search``, ``gslam tune`` and ``gslam fit-motion``: the commands that choose a
config's values from a log (``gslam_jax.tuning``) and write the config they chose."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from gslam_jax import choices
from gslam_jax.app.arguments import (add_deprecated, add_shared, add_source_arguments,
                                     config_and_run, positive_float, positive_int, spelled)
from gslam_jax.app.outputs import json_ready
from gslam_jax.app.progress import ProgressBar
from gslam_jax.app.results import results_folder, writing
from gslam_jax.config import ConfigError

if TYPE_CHECKING:
    from gslam_jax.tuning.motion_fit import MotionFit

__all__ = ["add_parsers", "cmd_fit_motion", "cmd_search", "cmd_tune"]


def add_parsers(sub) -> None:
    """The three commands' parsers on the ``gslam`` subparsers ``sub``."""
    p = sub.add_parser("search", help="batched parameter search (vmapped/sharded over sets)",
                       description="Batched parameter search (vmapped/sharded over the sets). "
                       "--out holds results.csv, results.json and best.toml (the config with "
                       "the best values, for --config).")
    add_source_arguments(p)
    p.add_argument("--space", type=Path, required=True, help="TOML search space (see "
                   "configs/search_example.toml)")
    p.add_argument("--design", choices=choices.SEARCH_DESIGNS, help="how the parameter sets "
                   "are drawn from the space (default: the space file's design, else halton)")
    p.add_argument("--n", type=positive_int, help="number of parameter sets (default: the "
                   "space file's n, else 64)")
    p.add_argument("--objective", choices=choices.SEARCH_OBJECTIVES, help="what ranks the sets: "
                   "rms, position RMS against ground truth (m), or the filter's log likelihood "
                   "(default: the space file's objective, else rms)")
    p.add_argument("--score-path", choices=choices.SCORE_PATHS,
                   help="path scored by rms: final best particle or weighted mean "
                   "(default: [filter] estimate)")
    p.add_argument("--batch", type=positive_int, help="parameter sets per chunk")
    add_shared(p, "--out", "--overwrite")
    p.set_defaults(func=cmd_search)

    p = sub.add_parser("tune", help="gradient tuning of the noise parameters with optax",
                       description="Gradient tuning of the noise parameters with optax. --out "
                       "holds tuned.toml (a config for --config) and tuned.json.")
    add_source_arguments(p)
    p.add_argument("--objective", choices=choices.TUNE_OBJECTIVES, default="loglik",
                   help="what the gradient steps improve (default loglik)")
    p.add_argument("--optimizer", default="adam", help="an optax optimiser by name whose "
                   "update needs only the gradient (adam, sgd, ...; lbfgs is refused)")
    p.add_argument("--lr", type=positive_float, default=0.05, help="learning rate (> 0)")
    p.add_argument("--steps", type=positive_int, default=100,
                   help="optimiser steps (default 100)")
    p.add_argument("--params", help="comma-separated names (default: the objective's)")
    p.add_argument("--runs-per-step", type=positive_int, default=4,
                   help="filter runs averaged per step (default 4)")
    p.add_argument("--crn", action="store_true", help="common random numbers across steps")
    add_shared(p, "--out", "--overwrite")
    p.set_defaults(func=cmd_tune)

    p = sub.add_parser("fit-motion", help="fit the [motion] alphas to the VO errors of a log "
                       "with ground truth (maximum likelihood of eqs. 2-3; and fallback_scale "
                       "to the fallback odometry's frames, when it has some), or without it to "
                       "the filter's evidence (--evidence)")
    add_source_arguments(p)
    p.add_argument("--window", type=positive_int, help="fit the errors summed over this many "
                   "consecutive frames (default: the frames between two local maps, so that "
                   "correlated VO errors are fitted at the spread the filter's updates see)")
    p.add_argument("--evidence", action="store_true", help="no ground truth: scale the "
                   "config's alphas together by the factor with the highest log evidence of "
                   "the filter (fixed tempering; gslam_jax/tuning/evidence_fit.py)")
    p.add_argument("--factors", type=positive_float, nargs="+", help="--evidence: the factors "
                   "tried (default: 1/64, 1/32, ..., 16)")
    p.add_argument("--evidence-seeds", type=int, nargs="+", metavar="SEED",
                   help="--evidence: filter seeds the log evidence is averaged over "
                   "(default 0 1 2)")
    add_shared(p, "--save-config", "--overwrite")
    add_deprecated(p, "--out", "use --save-config FILE.toml (--out is a results folder in "
                   "the other commands)", dest="save_config", type=Path)
    p.set_defaults(func=cmd_fit_motion)


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
            config, run = config_and_run(args)
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
            config, run = config_and_run(args)
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
                 "docs/notebook/real-data.md). The evidence fit is for the point sensor")
    return fit.config(config), text


def cmd_fit_motion(args: argparse.Namespace) -> int:
    from gslam_jax.app.outfile import check_output_file, write_text_atomic
    from gslam_jax.config import MotionSection, config_to_toml, section_to_toml
    from gslam_jax.tuning.motion_fit import fallback_scale, fit_run

    out, option = args.save_config, spelled(args, "save_config", "--save-config")
    if out is not None:  # a folder, a read-only place, an existing file: refused before the fit
        check_output_file(out, option, args.overwrite)
    if not args.evidence and (args.factors or args.evidence_seeds):
        raise ConfigError("--factors and --evidence-seeds go with --evidence")
    if args.evidence and args.window is not None:
        raise ConfigError("--window is the fit to the ground truth's; --evidence has none")
    config, run = config_and_run(args)
    if args.evidence:
        fitted, text = _evidence_fit(run, config, args)
    else:
        fit = fit_run(run, args.window)
        scale = fallback_scale(run, fit)
        fitted = dataclasses.replace(config, motion=MotionSection(
            alpha_d=fit.alpha_d, alpha_theta_d=fit.alpha_theta_d, alpha_theta=fit.alpha_theta,
            alpha_cross=fit.alpha_cross,
            fallback_scale=config.motion.fallback_scale if scale is None else scale))
        text = _fit_text(fit, run.num_frames)
        failed = 0 if run.vo_failed is None else int(np.sum(run.vo_failed))
        text += (f"\nfallback odometry ({failed} frames): its errors {scale:.3g}x the VO's "
                 "against the fitted stds (fallback_scale)" if scale is not None else
                 f"\nfallback odometry: {failed} frames, too few with ground truth to fit "
                 f"fallback_scale (kept at {config.motion.fallback_scale:g})")
    print(section_to_toml(fitted, "motion"))
    print(text)
    if out is not None:
        write_text_atomic(out, config_to_toml(fitted), option)
        print(f"config: {out} (the config with the fitted [motion], for --config)")
    return 0
