"""Shared by the experiments: a simulated run with known VO noise, objectives averaged over
filter keys, a run in a turned map frame, and the JSON report every experiment prints (and
optionally writes)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
from pathlib import Path
from typing import Callable

import jax
import numpy as np

from gslam_jax import choices
from gslam_jax.config import Config, layered_config
from gslam_jax.sim.courses import COURSES
from gslam_jax.datasets.sim import simulate_run
from gslam_jax.driver import device_arrays, sizing
from gslam_jax.driver.machine import environment
from gslam_jax.gridmap.grid import turn_poses
from gslam_jax.run import Run, load_run
from gslam_jax.sim.vonoise import VO_PROFILES
from gslam_jax.tuning.evaluation import evaluate
from gslam_jax.vo.localmap import LocalMapParams, localmap_params

ALPHAS = ("alpha_d", "alpha_theta_d", "alpha_theta")


def turned_run(run: Run, degrees: float) -> Run:
    """``run`` with its map frame turned by ``degrees`` about its start pose: the start heading
    and the ground truth turned with it; the controls and local maps (robot frame) as they are.
    The same log, seen in another frame: a filter that does not depend on the frame's
    orientation gives the same result up to the turn. On the frame's axes (``[map] axes =
    "frame"``) turning the frame moves the map's lattice against the terrain; on the robot's
    start axes ("start") it does not; shifting it does neither (the map's lattice is laid from
    the start pose, ``sizing.map_extent``)."""
    start = np.asarray(run.start_pose(), np.float64)
    a = math.radians(degrees)
    turned_start = start + np.array([0.0, 0.0, a])
    truth = run.ground_truth
    if truth is not None:
        shift = np.array([start[0], start[1], 0.0])
        truth = turn_poses(np.asarray(truth, np.float64) - shift, a) + shift
    return run._replace(initial_pose=turned_start, ground_truth=truth)


def add_known_noise_arguments(ap: argparse.ArgumentParser) -> None:
    """--course, --frames, --particles, --unknown, --white, --out."""
    ap.add_argument("--course", default="mars-yard-a")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--particles", type=int, default=64)
    ap.add_argument("--unknown", default="ignore", choices=choices.UNKNOWN_CELLS,
                    help="unknown-cell mode of the filter (eq. 30 or eq. 31)")
    ap.add_argument("--white", action="store_true",
                    help="VO noise of eqs. 1-3 only (no bias, no failures): the model is exact")
    ap.add_argument("--out", default=None, help="write the figures as JSON here")


def known_noise_run(args: argparse.Namespace) -> tuple[Run, dict[str, float]]:
    """The simulated run (seed 0, 2.5 m range, 32x32 local maps) and its true VO alphas."""
    lm = LocalMapParams(resolution=0.16, max_range=2.5, travel=1.0, cells=32)
    vo = VO_PROFILES[args.course]
    if args.white:
        vo = dataclasses.replace(vo, scale_bias_std=0.0, heading_bias_std=0.0, failure_rate=0.0)
    run, info = simulate_run(args.course, 0, lm, max_frames=args.frames, vo_noise=vo)
    return run, {k: getattr(info.vo_noise, k) for k in ALPHAS}


def key_averaged(run: Run, config: Config, names: tuple[str, ...] = ALPHAS
                 ) -> Callable[[np.ndarray, range, str], np.ndarray]:
    """f(values [P, d], keys, objective) -> [P]: the objective of each parameter set averaged
    over the filter keys (common random numbers across the sets for each key)."""
    inputs, cfg = device_arrays.run_arrays(run, config)
    base = sizing.filter_params(config)

    def f(values: np.ndarray, keys: range, objective: str) -> np.ndarray:
        return np.mean([evaluate(values, jax.random.key(k), inputs, base, names, cfg,
                                 objective) for k in keys], axis=0)

    return f


def alphas_of(config: Config) -> tuple[float, float, float]:
    """``[motion]`` alpha_d, alpha_theta_d, alpha_theta (``ALPHAS``)."""
    return tuple(getattr(config.motion, k) for k in ALPHAS)


def with_alphas(config: Config, alphas: tuple[float, float, float]) -> Config:
    """``config`` with ``[motion]`` alpha_d, alpha_theta_d, alpha_theta set to ``alphas``."""
    return dataclasses.replace(config, motion=dataclasses.replace(
        config.motion, **dict(zip(ALPHAS, alphas))))


def scaled_alphas(config: Config, scale: float) -> Config:
    """``config`` with its three ``ALPHAS`` times ``scale`` (the noise given too wide or too
    narrow by that factor)."""
    return with_alphas(config, tuple(a * scale for a in alphas_of(config)))


def add_case_arguments(ap: argparse.ArgumentParser) -> None:
    """--runs, --courses, --sim-seeds, --max-frames, --config, --set: the cases of
    ``cases_from_arguments``."""
    ap.add_argument("--runs", type=Path, nargs="*", default=[], help="Run files (.npz)")
    ap.add_argument("--courses", nargs="*", default=[], help="simulated courses")
    ap.add_argument("--sim-seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--max-frames", type=int, help="cut simulated courses")
    ap.add_argument("--config", type=Path, help="TOML config (a Table I config's course tables "
                    "apply to its courses)")
    ap.add_argument("--set", action="append", default=[])


def print_header(overrides: list[str]) -> None:
    """The first line of an experiment's output: date, CPUs, JAX version and the --set
    overrides, so that a figure can be traced to the machine and settings it came from."""
    env = environment()
    print(f"# {env['date']} | {env['cpus']} cpus | jax {env['jax']} | --set "
          f"{' '.join(overrides) or '(none)'}", flush=True)


def cases_from_arguments(args: argparse.Namespace) -> list[tuple[str, Run, Config]]:
    """(name, Run, config) of every Run file and every simulated course and sim seed named by
    ``add_case_arguments``' options, each with the config layered for it."""
    cases = [(str(p), load_run(p), layered_config(args.config, None, args.set, courses=COURSES))
             for p in args.runs]
    for course in args.courses:
        config = layered_config(args.config, course, args.set, courses=COURSES)
        for s in args.sim_seeds:
            run, _ = simulate_run(course, seed=s, params=localmap_params(config),
                                  max_frames=args.max_frames)
            cases.append((f"{course}/sim{s}", run, config))
    return cases


def report(figures: dict, out: str | None) -> dict:
    """Print the figures as JSON and write them to ``out`` if given."""
    text = json.dumps(figures, indent=2, default=float)
    print(text)
    if out:
        Path(out).write_text(text)
    return figures
