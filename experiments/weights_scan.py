"""Filter seeds on a saved Run (issue 16): VO-only RMS, Gamma-SLAM RMS of the reported path
([filter] estimate) and of all three estimates, and the ESS after each update (as a fraction
of J), for a config with ``--set`` overrides.

    python -m gslam_jax.app.cli run --source kitti --path ../shared/data/kitti-stereo-51 \
        --save-run /tmp/kitti51.npz
    python -m experiments.weights_scan /tmp/kitti51.npz --seeds 0 1 2 3 \
        [--config configs/kitti.toml] [--set filter.tempering=fixed] [--json out.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from gslam_jax.app.bench import environment
from gslam_jax.config import apply_overrides, load_config
from gslam_jax.driver import slam
from gslam_jax.evaluation import metrics
from gslam_jax.run import load_run


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_file", type=Path)
    ap.add_argument("--config", type=Path)
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    run = load_run(args.run_file)
    config = apply_overrides(load_config(args.config), args.set)
    env = environment()
    print(f"# {env['date']} | {env['cpus']} cpus | jax {env['jax']} | {args.run_file} | "
          f"--set {' '.join(args.set) or '(none)'}")
    print(f"{'seed':>4} {'VO RMS':>7} {'SLAM RMS':>8} {'ratio':>6} {'ESS min':>7} {'ESS med':>7} "
          f"{'<0.1J':>6} {'resamp':>6} {'phi med':>7}  RMS / VO of best, mean, smoothed")
    rows = []
    for seed in args.seeds:
        cfg = dataclasses.replace(config, filter=dataclasses.replace(config.filter, seed=seed))
        res = slam.run_slam(run, cfg)
        J = cfg.filter.particles
        ess = np.asarray(res.ess)[np.asarray(res.updated)] / J
        row = {"seed": seed, "vo_rms_m": metrics.rms_after_fit(res.vo_path, run.ground_truth),
               "slam_rms_m": metrics.rms_after_fit(res.path, run.ground_truth),
               **{f"{name}_rms_m": metrics.rms_after_fit(path, run.ground_truth) for name, path
                  in (("best", res.best_path), ("mean", res.mean_pose),
                      ("smoothed", res.smoothed_path))},
               "ess_min_frac": float(ess.min()), "ess_median_frac": float(np.median(ess)),
               "updates_below_0.1J": int(np.sum(ess < 0.1)), "updates": int(ess.size),
               "resamples": int(np.sum(res.resampled)),
               "exponent_median": float(np.median(res.exponent[np.asarray(res.updated)]))}
        rows.append(row)
        print(f"{seed:4d} {row['vo_rms_m']:7.3f} {row['slam_rms_m']:8.3f} "
              f"{row['slam_rms_m'] / row['vo_rms_m']:6.2f} {row['ess_min_frac']:7.3f} "
              f"{row['ess_median_frac']:7.3f} {row['updates_below_0.1J']:3d}/{row['updates']:<2d} "
              f"{row['resamples']:6d} {row['exponent_median']:7.3f}  "
              + ", ".join(f"{row[k + '_rms_m'] / row['vo_rms_m']:.2f}"
                          for k in ("best", "mean", "smoothed")))
    slam_rms = [r["slam_rms_m"] for r in rows]
    vo = rows[0]["vo_rms_m"]
    print(f"{config.filter.estimate} path: mean SLAM RMS {np.mean(slam_rms):.3f} m, worst "
          f"{np.max(slam_rms):.3f} m ({np.max(slam_rms) / vo:.2f} x VO)")
    if args.json:
        args.json.write_text(json.dumps({"environment": env, "overrides": args.set,
                                         "rows": rows}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
