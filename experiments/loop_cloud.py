"""What the particle cloud looks like on the way round a long loop: per stretch of travel, its
spread in position and heading, how near its nearest particle is to the truth, and the errors
of its mean, of the best particle's path and of the VO (all anchored at the true start, where
the filter starts). Asks whether a loop failed because no particle was near the truth at the
revisit (sample size) or because the weights chose badly.

    python -m experiments.loop_cloud --course arroyo-a --config configs/table1.toml \
        --circle 800 --seed 3 --set filter.unknown_cells=sample
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from experiments.loop_closure import START_M, circle_file, simulate_loop
from gslam_jax import loops, slam
from gslam_jax.config import layered_config


def cloud_rows(truth: np.ndarray, vo: np.ndarray, best: np.ndarray, poses: np.ndarray,
               ess: np.ndarray, resampled: np.ndarray, updated: np.ndarray,
               every_m: float = 50.0) -> list[dict]:
    """One row per ``every_m`` metres of true travel (and the last frame): the cloud
    ``poses`` [T, J, 3] at that frame against ``truth`` [T, 3], with the errors of ``vo`` and
    ``best`` [T, 3] there, and the resamplings and updates since the previous row."""
    arc = loops.arc_length(truth)
    rows, since, next_m = [], [0, 0], 0.0
    for t in range(len(truth)):
        since[0] += bool(resampled[t])
        since[1] += bool(updated[t])
        if arc[t] < next_m and t != len(truth) - 1:
            continue
        xy, true_xy = poses[t, :, :2], truth[t, :2]
        mean = xy.mean(axis=0)
        heading = np.angle(np.mean(np.exp(1j * poses[t, :, 2])))
        rows.append({
            "travel_m": float(arc[t]), "frame": t,
            "cloud_rms_m": float(np.sqrt(np.mean(np.sum((xy - mean) ** 2, axis=1)))),
            "heading_std_deg": float(np.degrees(np.std(np.angle(
                np.exp(1j * (poses[t, :, 2] - heading)))))),
            "nearest_particle_m": float(np.min(np.hypot(*(xy - true_xy).T))),
            "mean_error_m": float(np.hypot(*(mean - true_xy))),
            "best_error_m": float(np.hypot(*(best[t, :2] - true_xy))),
            "vo_error_m": float(np.hypot(*(vo[t, :2] - true_xy))),
            "ess": float(ess[t]), "resampled": since[0], "updates": since[1]})
        since, next_m = [0, 0], next_m + every_m
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--circle", type=float, default=800.0, help="circle perimeter, m")
    ap.add_argument("--seed", type=int, default=0, help="simulation and filter seed")
    ap.add_argument("--course", default="arroyo-a", help="world kind and VO noise")
    ap.add_argument("--config", type=Path)
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--every", type=float, default=50.0, help="metres of travel per row")
    ap.add_argument("--max-frames", type=int)
    args = ap.parse_args(argv)
    config = layered_config(args.config, args.course,
                            args.set + ["map.store=auto", f"filter.seed={args.seed}"])
    with tempfile.TemporaryDirectory() as tmp:
        run, config = simulate_loop(circle_file(Path(tmp), args.circle, 20.0), args.circle,
                                    args.seed, config, args.course, args.max_frames)
    chunks: list = []  # per chunk: the host-side StepInfo fields read below
    res = slam.run_slam(run, config, on_chunk=lambda r: chunks.append(
        (r.info.pose, r.info.ess, r.info.resampled, r.info.updated)))
    poses, ess, resampled, updated = (np.concatenate(x) for x in zip(*chunks))
    truth = np.asarray(run.ground_truth, np.float64)
    revisit = loops.find_revisit(truth, START_M, 0.5 * args.circle)
    if revisit is not None:
        print(f"revisit: frames {revisit.i} and {revisit.j}; revisit error best path "
              f"{loops.revisit_error(truth, res.best_path, revisit.i, revisit.j):.2f} m, VO "
              f"{loops.revisit_error(truth, res.vo_path, revisit.i, revisit.j):.2f} m")
    print("travel m | cloud rms m | heading std deg | nearest particle m | mean err m | "
          "best err m | VO err m | ESS | resampled / updates")
    for r in cloud_rows(truth, np.asarray(res.vo_path), np.asarray(res.best_path), poses, ess,
                        resampled, updated, args.every):
        print(f"{r['travel_m']:8.0f} | {r['cloud_rms_m']:11.2f} | {r['heading_std_deg']:15.2f} | "
              f"{r['nearest_particle_m']:18.2f} | {r['mean_error_m']:10.2f} | "
              f"{r['best_error_m']:10.2f} | {r['vo_error_m']:8.2f} | {r['ess']:5.1f} | "
              f"{r['resampled']} / {r['updates']}")


if __name__ == "__main__":
    main()
