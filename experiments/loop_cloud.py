"""What the particle cloud looks like on the way round a long loop: per stretch of travel, its
spread in position and heading, how near its nearest particle is to the truth, and the errors
of its mean, of the best particle's path and of the VO (all anchored at the true start, where
the filter starts), and how many particles are within 1 m of the truth and what share of the
weight they hold. Asks whether a loop failed because no particle was near the truth at the
revisit (sample size) or because the weights chose badly: from the approach frame
(``loop_closure.approach_frame``) on, a row every ``--zoom`` metres follows the near
particles through the revisit.

    python -m experiments.loop_cloud --course arroyo-a --config configs/table1.toml \
        --circle 800 --seed 3 --set filter.unknown_cells=sample
    python -m experiments.loop_cloud --course arroyo-a --config configs/table1.toml \
        --kitti ../shared/data/kitti-poses/00.txt --length 800 --seed 2 \
        --set filter.unknown_cells=sample
"""

from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path

import numpy as np

from experiments.common import scaled_alphas
from experiments.loop_closure import approach_frame, simulate_loop
from experiments.loop_paths import (START_M, Loop, add_vo_arguments, circle_loop, kitti_loops,
                                   vo_noise)
from gslam_jax.config import Config, layered_config
from gslam_jax.driver import slam
from gslam_jax.evaluation import loops
from gslam_jax.sim.courses import COURSES
from gslam_jax.gridmap import turn_poses
from gslam_jax.gridmap.grid import arc_length
from gslam_jax.run import Run
from gslam_jax.vo.localmap import localmap_params

NEAR_M = 1.0  # the closure's tolerance: particles this near the truth are counted


def cloud_rows(truth: np.ndarray, vo: np.ndarray, best: np.ndarray, poses: np.ndarray,
               ess: np.ndarray, resampled: np.ndarray, updated: np.ndarray,
               every_m: float = 50.0, log_w: np.ndarray | None = None,
               zoom_from: int | None = None, zoom_m: float = 2.0) -> list[dict]:
    """One row per ``every_m`` metres of true travel (and the last frame), and from frame
    ``zoom_from`` on (when given) one per ``zoom_m`` metres: the cloud ``poses`` [T, J, 3] at
    that frame against ``truth`` [T, 3], with the errors of ``vo`` and ``best`` [T, 3] there,
    the heading error of the particle nearest the truth, the particles within ``NEAR_M`` of
    the truth and the share of the normalised weights
    ``log_w`` [T, J] they hold (NaN without weights), and the resamplings and updates since
    the previous row."""
    arc = arc_length(truth)
    rows, since, next_m = [], [0, 0], 0.0
    for t in range(len(truth)):
        since[0] += bool(resampled[t])
        since[1] += bool(updated[t])
        if t == zoom_from:
            next_m = arc[t]
        if arc[t] < next_m and t != len(truth) - 1:
            continue
        zooming = zoom_from is not None and t >= zoom_from
        xy, true_xy = poses[t, :, :2], truth[t, :2]
        dist = np.hypot(*(xy - true_xy).T)
        near = dist <= NEAR_M
        share = float(np.sum(np.exp(log_w[t][near]))) if log_w is not None else math.nan
        mean = xy.mean(axis=0)
        heading = np.angle(np.mean(np.exp(1j * poses[t, :, 2])))
        rows.append({
            "travel_m": float(arc[t]), "frame": t,
            "cloud_rms_m": float(np.sqrt(np.mean(np.sum((xy - mean) ** 2, axis=1)))),
            "heading_std_deg": float(np.degrees(np.std(np.angle(
                np.exp(1j * (poses[t, :, 2] - heading)))))),
            "nearest_particle_m": float(dist.min()),
            "nearest_heading_deg": float(np.degrees(np.angle(
                np.exp(1j * (poses[t, int(np.argmin(dist)), 2] - truth[t, 2]))))),
            "within_1m": int(near.sum()),
            "weight_within_1m": share,
            "mean_error_m": float(np.hypot(*(mean - true_xy))),
            "best_error_m": float(np.hypot(*(best[t, :2] - true_xy))),
            "vo_error_m": float(np.hypot(*(vo[t, :2] - true_xy))),
            "ess": float(ess[t]), "resampled": since[0], "updates": since[1]})
        since = [0, 0]
        next_m = arc[t] + zoom_m if zooming else next_m + every_m
    return rows


def add_loop_arguments(ap: argparse.ArgumentParser) -> None:
    """The loop, world and filter settings shared by the loop tools (``simulated_loop``)."""
    ap.add_argument("--circle", type=float, default=800.0, help="circle perimeter, m")
    ap.add_argument("--kitti", type=Path, help="a KITTI pose file to cut the loop from instead "
                    "(``loop_paths.kitti_loops``: the simple loop nearest --length)")
    ap.add_argument("--length", type=float, default=800.0, help="KITTI loop length wanted, m")
    ap.add_argument("--radius", type=float, default=2.0, help="revisit radius of a KITTI cut, m")
    ap.add_argument("--seed", type=int, default=0, help="simulation and filter seed")
    ap.add_argument("--course", default="arroyo-a", help="world kind and VO noise")
    ap.add_argument("--config", type=Path)
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--max-frames", type=int)
    add_vo_arguments(ap)


def simulated_loop(args: argparse.Namespace) -> tuple[Loop, Run, Config]:
    """The loop of ``add_loop_arguments``' settings, its simulated Run and the config to filter
    it with, as ``loop_closure`` drives it: ``--set`` comes last, so that e.g.
    ``map.store=shared`` repeats a ``loop_closure`` run exactly, at the same ``--vo-scale``,
    ``--vo-failures`` and ``--noise-scale``."""
    config = scaled_alphas(layered_config(args.config, args.course,
                                          ["map.store=auto", f"filter.seed={args.seed}"]
                                          + args.set, courses=COURSES), args.noise_scale)
    noise = vo_noise(args.course, args.vo_scale, args.vo_failures)
    with tempfile.TemporaryDirectory() as tmp:
        if args.kitti is None:
            loop = circle_loop(Path(tmp), args.circle, 20.0)
        else:
            cuts = kitti_loops(Path(tmp), args.kitti, [args.length], args.radius, 20.0)
            if not cuts:
                raise SystemExit(f"{args.kitti}: no return within {args.radius} m to cut a "
                                 "loop from")
            loop = cuts[0]
            print(f"{args.kitti}: {loop.name}, a {loop.length_m:.1f} m loop")
        run, config = simulate_loop(loop.file, loop.length_m, args.seed, config, args.course,
                                    args.max_frames, vo_noise=noise)
    return loop, run, config


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_loop_arguments(ap)
    ap.add_argument("--every", type=float, default=50.0, help="metres of travel per row")
    ap.add_argument("--zoom", type=float, default=2.0,
                    help="metres of travel per row from the approach frame on")
    args = ap.parse_args(argv)
    loop, run, config = simulated_loop(args)
    chunks: list = []  # per chunk: the host-side StepInfo fields read below
    # the particles are filtered on the map lattice's axes: turned back into the run's frame,
    # where the truth, the best path and the VO path are
    res = slam.run_slam(run, config, on_chunk=lambda r: chunks.append(
        (turn_poses(r.info.pose, r.heading), r.info.log_w, r.info.ess, r.info.resampled,
         r.info.updated)))
    poses, log_w, ess, resampled, updated = (np.concatenate(x) for x in zip(*chunks))
    truth = np.asarray(run.ground_truth, np.float64)
    revisit = loops.find_revisit(truth, START_M, 0.5 * loop.length_m)
    zoom_from = None
    if revisit is not None:
        zoom_from = approach_frame(truth, revisit, localmap_params(config).max_range)
        verdict = loops.closure(run, np.asarray(res.best_path), revisit)  # loop_closure's
        print(f"revisit: frames {revisit.i} and {revisit.j} (approach frame {zoom_from}); "
              f"best path: revisit error {verdict.error_m:.2f} m, map offset "
              f"{verdict.map_offset_m:.2f} m, {'closed' if verdict.closed else 'open'}; VO "
              f"revisit error {loops.revisit_error(truth, res.vo_path, revisit.i, revisit.j):.2f}"
              " m")
    print("travel m | cloud rms m | heading std deg | nearest particle m (heading err deg) | "
          "within 1 m (weight) | mean err m | best err m | VO err m | ESS | resampled / updates")
    for r in cloud_rows(truth, np.asarray(res.vo_path), np.asarray(res.best_path), poses, ess,
                        resampled, updated, args.every, log_w, zoom_from, args.zoom):
        print(f"{r['travel_m']:8.0f} | {r['cloud_rms_m']:11.2f} | {r['heading_std_deg']:15.2f} | "
              f"{r['nearest_particle_m']:18.2f} ({r['nearest_heading_deg']:+5.2f}) | "
              f"{r['within_1m']:6d} ({r['weight_within_1m']:.3f})"
              f" | {r['mean_error_m']:10.2f} | {r['best_error_m']:10.2f} | "
              f"{r['vo_error_m']:8.2f} | {r['ess']:5.1f} | {r['resampled']} / {r['updates']}")


if __name__ == "__main__":
    main()
