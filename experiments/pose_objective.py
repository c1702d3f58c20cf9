"""The pose objective: where the score of each local map peaks, with the map built at the true
poses, and how sharp it is per direction. This is what an observation-informed proposal can use.

For every update, in order, the maps of one particle hold every earlier local map placed at its
true pose (the filter's own update, ``rbpf.update``, with the particle set to the truth). The
update's local map is then scored over a grid of offsets around the true pose, in the robot
frame (along-track, across-track, heading), with the filter's own footprint reads and eq. 26
with eq. 30 / 31 (``read_footprints``, ``log_lambda``; untempered), all offsets in one jitted
call. Per update: the peak's offset from the truth, whether it lies on the grid's edge per
axis, and the information per axis at the peak (-d2 log lambda / d axis^2, by second
differences), beside the motion prior's variance accumulated since the last update for the
configured alphas (their product: how much sharper the score is than the prior that way).

    python -m experiments.pose_objective --run /tmp/k51.npz --self-check
    python -m experiments.pose_objective --run /tmp/k51.npz --span-m 0.16 --step-m 0.16 \
        --span-rad 0.01 --step-rad 0.0005 --frame-turns 0 0.5 2 11.25 22.5 45 67.5 90
    python -m experiments.pose_objective --course mars-yard-a --sim-seed 0 --max-frames 400 \
        --config configs/table1.toml --vo-noise-scale 0 --json out.json

(a Run file from ``gslam run --source kitti --path ../shared/data/kitti-stereo-51 --save-run
/tmp/k51.npz``; ``--vo-noise-scale 0``: the simulator's VO without noise, biases or failures;
``--disparity-std 0``: its point sensor without stereo noise.)

Each line: source, frame, local map, observed cells with a prior at the truth, the peak's offset
(m, m, rad), its edge flags, the information per axis at the peak and its ratio to the prior's
precision. The summary (JSON): updates scored (some overlap, a score that is not constant),
``within``: the fraction whose peak is within one map cell (along and across) and 0.01 rad of
the truth, per axis the fraction on the edge, the peak's mean offset and median |offset|, the
median information at the peak and of a parabola fitted along the axis through the truth over
the whole grid (``fitted``: the shape a proposal's fit sees, where the second difference at the
peak sees the score's roughness), each also times the prior's variance (``over_prior``); with
``--self-check`` the fraction of local maps that, scored against a map of themselves alone,
peak at zero. A tie for the maximum (a shift that moves no local cell to another map cell) goes
to the tied offset nearest the truth.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from functools import partial
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array, lax

from experiments.common import turned_run
from experiments.pose_grid import (  # noqa: F401  (the experiment's API)
    AXES,
    HEADING_TOL,
    Grid,
    fitted_information,
    information,
    offset_grid,
    peak,
)
from gslam_jax import rbpf
from gslam_jax.config import Config, apply_overrides, layered_config
from gslam_jax.sim.courses import COURSES
from gslam_jax.datasets.sim import simulate_run
from gslam_jax.driver import observations, sizing
from gslam_jax.driver.machine import environment
from gslam_jax.rbpf import cells, maps
from gslam_jax.rbpf.footprint import compact_observation, read_footprints
from gslam_jax.rbpf.importance import log_lambda
from gslam_jax.rbpf.proposal import motion_covariance_step
from gslam_jax.run import Run, load_run
from gslam_jax.sim.sensor import SensorParams
from gslam_jax.sim.vonoise import VO_PROFILES
from gslam_jax.vo.localmap import localmap_params


class UpdateScore(NamedTuple):
    """The pose objective of one update (per-axis entries in ``AXES`` order)."""

    frame: int
    local_map: int
    overlap: int             # observed local cells with a prior at the truth
    score_range: float       # max - min of log lambda over the grid (0: no information)
    peak: np.ndarray         # [3] offset of the maximum from the truth
    edge: np.ndarray         # [3] bool: the maximum lies on the grid's edge on that axis
    information: np.ndarray  # [3] -d2 log lambda / d axis^2 at the peak (nearest interior point)
    fitted: np.ndarray       # [3] -d2/d axis^2 of a parabola fitted along each axis through the
                             # truth, over the whole grid (the score's shape at the grid's scale)
    prior_var: np.ndarray    # [3] the motion prior's variance since the last update (robot frame)

    @property
    def scored(self) -> bool:
        return self.overlap > 0 and self.score_range > 0

    def within(self, resolution: float) -> bool:
        """The peak lies within one map cell (along and across) and 0.01 rad of the truth."""
        tol = np.array([resolution, resolution, HEADING_TOL]) + 1e-6
        return bool(np.all(np.abs(self.peak) <= tol))

    def row(self) -> dict:
        d = {"frame": self.frame, "local_map": self.local_map, "overlap": self.overlap,
             "score_range": self.score_range}
        for name, v in (("peak", self.peak), ("edge", self.edge),
                        ("information", self.information), ("fitted", self.fitted),
                        ("prior_var", self.prior_var)):
            d.update({f"{name}_{a}": (bool(x) if v.dtype == bool else float(x))
                      for a, x in zip(AXES, v)})
        return d


def truth_config(run: Run, config: Config) -> tuple[rbpf.FilterConfig, rbpf.FilterParams]:
    """One particle in a dense map (the filter's ``sizing.filter_config`` otherwise), the map
    widened to hold the true path as well as the VO path, and the config's parameters."""
    one = apply_overrides(config, ["filter.particles=1", "filter.proposal=motion",
                                   "map.store=dense"])
    cfg = sizing.filter_config(one, run)
    gt = np.asarray(run.ground_truth, np.float64)
    path = np.concatenate([run.vo_poses(), gt[np.isfinite(gt[:, :2]).all(axis=1)]])
    extent = sizing.map_extent(path, cfg.local_size, cfg.resolution, config.map.margin, cfg.window)
    cfg = cfg._replace(map_shape=extent.shape, map_origin=extent.origin).validate()
    return cfg, sizing.filter_params(one)


def _poses(centre: Array, along: Array, across: Array, heading: Array) -> Array:
    """World poses [na, nc, 3] at robot-frame offsets (along, across) from ``centre`` with
    heading centre + ``heading`` []."""
    A, C = jnp.meshgrid(along, across, indexing="ij")
    c, s = jnp.cos(centre[2]), jnp.sin(centre[2])
    return jnp.stack([centre[0] + c * A - s * C, centre[1] + s * A + c * C,
                      jnp.broadcast_to(centre[2] + heading, A.shape)], -1)


@partial(jax.jit, static_argnames=("cfg",))
def score_grid(store: maps.Maps, centre: Array, local_obs: Array, unknown_u: Array,
               along: Array, across: Array, heading: Array, params: rbpf.FilterParams,
               cfg: rbpf.FilterConfig) -> tuple[Array, Array]:
    """log lambda [na, nc, nh] of ``local_obs`` [L, L, 2] at every grid offset from ``centre``
    against particle 0's maps (one heading after another, each a batch of every position), and
    the observed cells with a prior at ``centre`` []. ``unknown_u`` [1, D]: the update's
    unknown-cell draws, shared by every offset."""
    obs = compact_observation(local_obs, cfg)
    log_v = cells.log_v_obs(obs.k, obs.S)
    rows = jnp.zeros((1,), jnp.int32)

    def footprint(pose: Array):
        f = read_footprints(store, pose[None], rows, unknown_u, obs, cfg)
        return jax.tree.map(lambda x: x[0], f)

    def plane(h: Array) -> Array:
        poses = _poses(centre, along, across, h)
        f = jax.vmap(footprint)(poses.reshape(-1, 3))
        return log_lambda(f, log_v, params, cfg).reshape(poses.shape[:2])

    at = footprint(centre)
    overlap = jnp.sum((at.k_obs > 0) & (at.k_prior > 0))
    return jnp.moveaxis(lax.map(plane, heading), 0, -1), overlap


_update = jax.jit(rbpf.update, static_argnames=("cfg",))


def prior_variances(controls: np.ndarray, obs_index: np.ndarray, start: np.ndarray,
                    truth: np.ndarray, params: rbpf.FilterParams) -> np.ndarray:
    """[T, 3] variance of the motion prior (eqs. 1-3, linearised at the true poses) accumulated
    from the previous update frame (obs_index >= 0) to each frame, in the robot frame at the
    true heading (along, across, heading)."""
    prev = np.concatenate([np.asarray(start, np.float64)[None], truth[:-1]])

    def frame(cov, xs):
        pose, u, r = xs
        cov = motion_covariance_step(pose, cov, u, params.motion)
        return jnp.where(r, jnp.zeros_like(cov), cov), cov

    _, covs = lax.scan(frame, jnp.zeros((3, 3), jnp.float32),
                       (jnp.asarray(np.nan_to_num(prev), jnp.float32),
                        jnp.asarray(controls, jnp.float32), jnp.asarray(obs_index >= 0)))
    covs = np.asarray(covs, np.float64)
    c, s = np.cos(truth[:, 2]), np.sin(truth[:, 2])
    R = np.zeros(covs.shape)
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, s, -s, c, 1.0
    robot = R @ covs @ np.swapaxes(R, 1, 2)
    return np.diagonal(robot, axis1=1, axis2=2)


def compose(pose: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """``pose`` moved by a robot-frame ``offset`` (along, across, heading)."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return np.array([pose[0] + c * offset[0] - s * offset[1],
                     pose[1] + s * offset[0] + c * offset[1], pose[2] + offset[2]])


def pose_objective(run: Run, config: Config, grid: Grid,
                   centre_offset: np.ndarray | None = None) -> list[UpdateScore]:
    """The pose objective of every update of ``run`` whose true pose is known (see the module
    docstring). ``centre_offset`` (robot frame) moves the scoring grid's centre off the truth
    (a check: the peak then moves by the inverse offset); the maps stay at the truth."""
    if run.ground_truth is None:
        raise ValueError("the pose objective needs a run with ground truth")
    cfg, params = truth_config(run, config)
    truth = np.asarray(run.ground_truth, np.float64)
    local_obs = observations.map_observations(run, config)
    prior = prior_variances(run.controls, np.asarray(run.obs_index), run.start_pose(), truth,
                            params)
    state = rbpf.init(cfg, jnp.asarray(run.start_pose(), jnp.float32))
    key = jax.random.key(config.filter.seed)
    axes = [jnp.asarray(a, jnp.float32) for a in grid]
    out = []
    for t in np.flatnonzero(np.asarray(run.obs_index) >= 0):
        if not np.isfinite(truth[t]).all():
            continue
        m = int(run.obs_index[t])
        u = rbpf.update_noise(jax.random.fold_in(key, int(t)), cfg).unknown_u
        centre = truth[t] if centre_offset is None else compose(truth[t], centre_offset)
        scores, overlap = score_grid(state.maps, jnp.asarray(centre, jnp.float32), local_obs[m],
                                     u, *axes, params, cfg)
        scores = np.asarray(scores, np.float64)
        index, offset = peak(scores, grid)
        out.append(UpdateScore(
            int(t), m, int(overlap), float(scores.max() - scores.min()), offset,
            (index == 0) | (index == np.array(scores.shape) - 1),
            information(scores, index, grid), fitted_information(scores, grid), prior[t]))
        state = state._replace(pose=jnp.asarray(truth[t], jnp.float32)[None])
        state, _ = _update(state, local_obs[m], u, params, cfg)
    return out


def self_peaks(run: Run, config: Config, grid: Grid) -> np.ndarray:
    """[U, 3] the peak's offset when each local map is scored against a map of itself alone,
    placed at its true pose: a check of the placement conventions of scoring and writing (a
    wrong one moves every peak). Not every peak is at zero: eq. 30 averages over the cells that
    overlap, so a shift that moves a few poorly matched cells off the map can score higher."""
    cfg, params = truth_config(run, config)
    truth = np.asarray(run.ground_truth, np.float64)
    local_obs = observations.map_observations(run, config)
    empty = rbpf.init(cfg)
    u = rbpf.update_noise(jax.random.key(config.filter.seed), cfg).unknown_u
    axes = [jnp.asarray(a, jnp.float32) for a in grid]
    out = []
    for t in np.flatnonzero(np.asarray(run.obs_index) >= 0):
        if not np.isfinite(truth[t]).all():
            continue
        m = int(run.obs_index[t])
        pose = jnp.asarray(truth[t], jnp.float32)
        state, _ = _update(empty._replace(pose=pose[None]), local_obs[m], u, params, cfg)
        scores, _ = score_grid(state.maps, pose, local_obs[m], u, *axes, params, cfg)
        out.append(peak(np.asarray(scores, np.float64), grid)[1])
    return np.array(out).reshape(-1, 3)


def summary(scores: list[UpdateScore], resolution: float) -> dict:
    """The figures over the scored updates (``UpdateScore.scored``)."""
    used = [s for s in scores if s.scored]
    d: dict = {"updates": len(scores), "scored": len(used)}
    if not used:
        return d
    peaks = np.array([s.peak for s in used])
    info = np.array([s.information for s in used])
    fitted = np.array([s.fitted for s in used])
    var = np.array([s.prior_var for s in used])
    with np.errstate(invalid="ignore"):
        ratio = np.where(var > 0, info * var, np.nan)
        fitted_ratio = np.where(var > 0, fitted * var, np.nan)
    d["within"] = float(np.mean([s.within(resolution) for s in used]))
    for a, name in enumerate(AXES):
        d[f"edge_{name}"] = float(np.mean([s.edge[a] for s in used]))
        d[f"mean_peak_{name}"] = float(np.mean(peaks[:, a]))
        d[f"median_abs_peak_{name}"] = float(np.median(np.abs(peaks[:, a])))
        d[f"median_prior_std_{name}"] = float(np.median(np.sqrt(var[:, a])))
        for key, v in (("information", info), ("over_prior", ratio), ("fitted", fitted),
                       ("fitted_over_prior", fitted_ratio)):
            col = v[:, a]
            d[f"median_{key}_{name}"] = (float(np.median(col[np.isfinite(col)]))
                                         if np.isfinite(col).any() else None)
    return d


def _sim(course: str, seed: int, config: Config, max_frames: int | None, noise_scale: float,
         disparity_std: float | None = None) -> Run:
    """The simulated course with its VO noise scaled (0: none, no failures either) and the
    point sensor's disparity noise replaced where given."""
    vo = VO_PROFILES[course].scaled(noise_scale)
    if noise_scale == 0:
        vo = dataclasses.replace(vo, failure_rate=0.0)
    params = localmap_params(config)
    sensor = SensorParams(max_range=params.max_range)
    if disparity_std is not None:
        sensor = dataclasses.replace(sensor, disparity_std=disparity_std)
    run, _ = simulate_run(course, seed=seed, params=params, sensor=sensor,
                          max_frames=max_frames, vo_noise=vo)
    return run


def _print(name: str, s: UpdateScore) -> None:
    flags = "".join(c if e else "." for c, e in zip("ach", s.edge))
    info = " ".join(f"{x:9.3g}" for x in s.information)
    ratio = " ".join(f"{x * v:8.3g}" if v > 0 else f"{'-':>8}"
                     for x, v in zip(s.information, s.prior_var))
    print(f"{name:>22} {s.frame:5d} {s.local_map:4d} {s.overlap:6d} {s.peak[0]:+6.2f} "
          f"{s.peak[1]:+6.2f} {s.peak[2]:+7.3f} {flags} {info}  {ratio}"
          f"{'' if s.scored else '  (not scored)'}", flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, action="append", default=[], help="Run file (.npz) "
                    "with ground truth")
    ap.add_argument("--course", action="append", default=[], help="simulated course")
    ap.add_argument("--sim-seed", type=int, nargs="+", default=[0])
    ap.add_argument("--max-frames", type=int, help="cut simulated courses")
    ap.add_argument("--vo-noise-scale", type=float, default=1.0, help="the simulated VO "
                    "noise times this (0: none, no failures either)")
    ap.add_argument("--disparity-std", type=float, help="the simulated point sensor's "
                    "disparity noise (pixels; default: the sensor's)")
    ap.add_argument("--config", type=Path, help="TOML config (a Table I config's course tables "
                    "apply to its courses)")
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--span-m", type=float, default=0.5, help="grid half-width along and across")
    ap.add_argument("--step-m", type=float, default=0.04)
    ap.add_argument("--span-rad", type=float, default=0.05, help="grid half-width in heading")
    ap.add_argument("--step-rad", type=float, default=0.005)
    ap.add_argument("--self-check", action="store_true", help="also score each local map "
                    "against a map of itself alone (summary: the fraction peaking at zero)")
    ap.add_argument("--frame-turns", type=float, nargs="+", default=[0.0], metavar="DEG",
                    help="score each case with its map frame turned by each of these angles "
                    "(common.turned_run): where the peak's heading sits then depends on the "
                    "angle between the local maps' lattice and the map's")
    ap.add_argument("--json", type=Path, help="also write every row here (JSON lines)")
    args = ap.parse_args(argv)
    env = environment()
    print(f"# {env['date']} | {env['processor']} | {env['usable_cpus']}/{env['cpus']} cpus | "
          f"jax {env['jax']} | --set {' '.join(args.set) or '(none)'}", flush=True)
    grid = offset_grid(args.span_m, args.step_m, args.span_rad, args.step_rad)
    print(f"# grid {len(grid.along)} x {len(grid.across)} x {len(grid.heading)}: "
          f"+-{grid.along[-1]:.3g} m, +-{grid.heading[-1]:.3g} rad", flush=True)
    cases = [(str(p), load_run(p), layered_config(args.config, None, args.set, courses=COURSES))
             for p in args.run]
    for course in args.course:
        config = layered_config(args.config, course, args.set, courses=COURSES)
        for s in args.sim_seed:
            run = _sim(course, s, config, args.max_frames, args.vo_noise_scale,
                       args.disparity_std)
            disparity = "" if args.disparity_std is None else f"/d{args.disparity_std:g}"
            cases.append((f"{course}/sim{s}/vo{args.vo_noise_scale:g}{disparity}", run, config))
    cases = [(name if turn == 0 else f"{name}@{turn:g}deg", turned_run(run, turn), config)
             for name, run, config in cases for turn in args.frame_turns]
    out = args.json.open("w") if args.json else None
    print(f"{'source':>22} {'frame':>5} {'map':>4} {'prior':>6} {'along':>6} {'across':>6} "
          f"{'head':>7} ach {'info along':>9} {'across':>9} {'heading':>9}  "
          f"{'x prior':>8} {'':>8} {'':>8}")
    for name, run, config in cases:
        scores = pose_objective(run, config, grid)
        for s in scores:
            _print(name, s)
            if out:
                out.write(json.dumps({"source": name, **s.row()}) + "\n")
        summ = summary(scores, config.map.resolution)
        if args.self_check:
            own = self_peaks(run, config, grid)
            summ["self_at_zero"] = float(np.mean(np.all(own == 0, axis=1)))
        print(f"# {name}: {json.dumps(summ)}", flush=True)
        if out:
            out.write(json.dumps({"source": name, "summary": True, **summ}) + "\n")
            out.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
