"""The motion proposal against the observation-informed one ([filter] proposal), per seed:
Gamma-SLAM RMS and final drift against VO-only, with the motion noise scaled from its
calibrated value (robustness), on Run files and simulated courses.

    python -m gslam_jax.app.cli run --source kitti --path ../shared/data/kitti-stereo-51 \
        --save-run /tmp/kitti51.npz
    python -m experiments.proposal_compare --runs /tmp/kitti51.npz --seeds 0 1 2 3 4 5 6 7
    python -m experiments.proposal_compare --courses mars-yard-a arroyo-a maze --sim-seeds 0 \
        --noise-scale 0.3 1 10 --config configs/table1.toml --max-frames 600 --json out.json

Each line: source, noise scale, proposal, particles, filter seed, VO RMS, SLAM RMS, their ratio,
final drift of both (% of the true distance), the rotation of the rigid fit of each path to the
ground truth (a path rotated as a whole drifts at its end while its RMS after the fit stays
small), the length of each path against the true length (a path shortened or stretched as a
whole: the rigid fit cannot take that out), filter seconds (after compilation).
``--frame-turns`` also runs each case with its map frame turned by each angle about the start
(``common.turned_run``: the start heading and the ground truth turned, the log as it is): the
result should not depend on it (docs/notebook/results.md,
"The map frame's orientation"); the fit turn is then the path's turn against the truth in
every frame.

    python -m experiments.proposal_compare --runs /tmp/kitti51.npz --proposals motion \
        --frame-turns 0 22.5 45 90 --seeds 0 1 2 3 4 5 6 7
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

from gslam_jax.config import apply_overrides
from gslam_jax.driver import slam
from gslam_jax.evaluation import metrics
from gslam_jax.run import known_positions

from experiments.common import (add_case_arguments, cases_from_arguments, print_header,
                                scaled_alphas, turned_run)


def case_row(name, run, config, scale, proposal, seed) -> dict:
    """One filter run of ``run`` (its motion noise scaled by ``scale``, ``proposal``, filter
    ``seed``) against VO-only: RMS, final drift and the rigid fit's turn of both, and time."""
    cfg = apply_overrides(scaled_alphas(config, scale), [f"filter.proposal={proposal}",
                                                   f"filter.seed={seed}"])
    t0 = time.perf_counter()
    res = slam.run_slam(run, cfg)
    wall = time.perf_counter() - t0
    paths = {"vo": res.vo_path, "slam": res.path}
    err = metrics.errors_over_known_frames(paths, run.ground_truth)
    drift = metrics.drift_over_known_frames(paths, run.ground_truth)
    known = known_positions(run.ground_truth)
    turn = {name: math.degrees(metrics.rigid_fit_2d(p[known], run.ground_truth[known]).angle)
            for name, p in paths.items()}
    true_length = metrics.path_length(run.ground_truth[known])
    length = {name: 100.0 * (metrics.path_length(p[known]) / true_length - 1.0)
              for name, p in paths.items()}
    return {"source": name, "noise_scale": scale, "proposal": proposal,
            "particles": cfg.filter.particles, "seed": seed, "vo_rms_m": err["vo_rms_m"],
            "slam_rms_m": err["slam_rms_m"], "ratio": err["slam_rms_m"] / err["vo_rms_m"],
            "vo_drift_pct": drift.get("vo_drift_pct"),
            "slam_drift_pct": drift.get("slam_drift_pct"),
            "vo_fit_turn_deg": turn["vo"], "slam_fit_turn_deg": turn["slam"],
            "vo_length_pct": length["vo"], "slam_length_pct": length["slam"],
            "filter_seconds": res.seconds, "wall_seconds": wall,
            "resampling_events": int(res.resampled.sum()),
            # the particles' factor on the given motion stds at the end ([motion] noise_spread)
            "final_noise_scale": float(res.noise_scale[-1])}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_case_arguments(ap)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3], help="filter seeds")
    ap.add_argument("--noise-scale", type=float, nargs="+", default=[1.0])
    ap.add_argument("--proposals", nargs="+", default=["motion", "informed"])
    ap.add_argument("--frame-turns", type=float, nargs="+", default=[0.0], metavar="DEG",
                    help="run each case with its map frame turned by each of these angles")
    ap.add_argument("--json", type=Path, help="also write every row here (JSON lines)")
    args = ap.parse_args()
    print_header(args.set)
    cases = [(name if turn == 0 else f"{name}@{turn:g}deg", turned_run(run, turn), config)
             for name, run, config in cases_from_arguments(args) for turn in args.frame_turns]
    out = args.json.open("w") if args.json else None
    for name, run, config in cases:
        for scale in args.noise_scale:
            for proposal in args.proposals:
                for seed in args.seeds:
                    row = case_row(name, run, config, scale, proposal, seed)
                    print(f"{name:>22} x{scale:<4g} {proposal:>8} J={row['particles']:<4} "
                          f"seed {seed}: VO {row['vo_rms_m']:.3f} SLAM {row['slam_rms_m']:.3f} "
                          f"({row['ratio']:.2f}x) drift VO {row['vo_drift_pct']:.2f} % SLAM "
                          f"{row['slam_drift_pct']:.2f} % fit turn VO "
                          f"{row['vo_fit_turn_deg']:+.2f} "
                          f"SLAM {row['slam_fit_turn_deg']:+.2f} deg length VO "
                          f"{row['vo_length_pct']:+.2f} % SLAM {row['slam_length_pct']:+.2f} %  "
                          f"noise x{row['final_noise_scale']:.2f}  {row['wall_seconds']:.1f} s",
                          flush=True)
                    if out:
                        out.write(json.dumps(row) + "\n")
                        out.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
