"""Is the map likelihood itself biased on a Run? (issue 16) Replace the VO controls by the
ground-truth increments (perfect odometry) and run the filter: with an unbiased likelihood the
particles stay on the truth, so Gamma-SLAM's RMS measures how far the weights pull them off.
Also prints the tempering exponents the adaptive rule chose (their median is the factor by
which the paper's 1/beta overstates the effective number of independent cells).

    python -m experiments.oracle_odometry /tmp/kitti51.npz --seeds 0 1 2 3 [--set ...]
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from gslam_jax.config import apply_overrides, load_config
from gslam_jax.driver import slam
from gslam_jax.evaluation import metrics
from gslam_jax.run import load_run


def gt_controls(gt: np.ndarray) -> np.ndarray:
    """Robot-frame increments between consecutive ground-truth poses (controls[0] = 0)."""
    d = np.diff(gt, axis=0)
    c, s = np.cos(gt[:-1, 2]), np.sin(gt[:-1, 2])
    u = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1],
                  np.angle(np.exp(1j * d[:, 2]))], axis=1)
    return np.concatenate([np.zeros((1, 3)), u]).astype(np.float32)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_file", type=Path)
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    args = ap.parse_args()
    run = load_run(args.run_file)
    gt = np.asarray(run.ground_truth, np.float64)
    oracle = run._replace(controls=gt_controls(gt), initial_pose=gt[0])
    config = apply_overrides(load_config(None), args.set)
    print(f"# {args.run_file} --set {' '.join(args.set) or '(none)'}; odometry = ground truth")
    for seed in args.seeds:
        cfg = dataclasses.replace(config, filter=dataclasses.replace(config.filter, seed=seed))
        res = slam.run_slam(oracle, cfg)
        ess = np.asarray(res.ess)[np.asarray(res.updated)] / cfg.filter.particles
        print(f"seed {seed}: odometry RMS {metrics.rms_after_fit(res.vo_path, gt):.3f} m, "
              f"Gamma-SLAM RMS {metrics.rms_after_fit(res.best_path, gt):.3f} m, "
              f"ESS median {np.median(ess):.2f} J, exponent median "
              f"{np.median(res.exponent[res.updated]):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
