"""Latency of the live API (``gslam_jax.Online``): a simulated course replayed frame by frame,
the wall time of every push (a frame with or without a local map) after the first (which
compiles), and the real-time factor (seconds of log per second of filter compute).
``--batch`` also runs ``slam.run_slam`` on the same frames, map extent and seed, and reports
the RMS errors after the rigid fit (paper 7.1) of both reported paths (``[filter] estimate``):
they are equal unless a setting differs online, as ``[filter] range_noise = "profile"`` does
(a running estimate there).

    python -m experiments.online_latency --frames 600 --particles 100
    python -m experiments.online_latency --config configs/table1.toml --frames 0 --batch

Prints a JSON report with the machine and versions (``machine.environment``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from gslam_jax.config import layered_config
from gslam_jax.sim.courses import COURSES
from gslam_jax.datasets.sim import simulate_run
from gslam_jax.driver import slam
from gslam_jax.driver.machine import environment
from gslam_jax.driver.online import Online
from gslam_jax.evaluation.metrics import rms_after_fit
from gslam_jax.vo.localmap import localmap_params


def _summary(seconds: np.ndarray) -> dict:
    if not seconds.size:
        return {"count": 0}
    ms = 1e3 * seconds
    return {"count": int(ms.size), "mean_ms": float(ms.mean()),
            "median_ms": float(np.median(ms)), "p95_ms": float(np.percentile(ms, 95)),
            "max_ms": float(ms.max())}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--course", default="mars-yard-a")
    ap.add_argument("--seed", type=int, default=0, help="the course's sim seed")
    ap.add_argument("--frames", type=int, default=600, help="0: the whole course")
    ap.add_argument("--particles", type=int, default=100)
    ap.add_argument("--config", type=Path, default=None,
                    help="TOML settings, [course.<name>.*] tables included (default: defaults)")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="override a setting (repeatable)")
    ap.add_argument("--batch", action="store_true",
                    help="also run the batch filter on the same frames; report both RMS")
    ap.add_argument("--size", type=float, default=100.0,
                    help="side in metres of the square map around the start")
    ap.add_argument("--store", default="dense", help="[map] store")
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON report here")
    args = ap.parse_args(argv)

    config = layered_config(args.config, args.course,  # with the course's own tables
                            [f"filter.particles={args.particles}", f"map.store={args.store}",
                             *args.set], courses=COURSES)
    run, _ = simulate_run(args.course, seed=args.seed, params=localmap_params(config),
                          max_frames=args.frames or None)
    # with --batch, the batch run's map extent, so that the two differ only in the filter
    live = (Online(config, start_pose=run.start_pose(),
                   filter_config=slam.run_filter_config(run, config)) if args.batch
            else Online(config, args.size, start_pose=run.start_pose()))
    for t in range(run.num_frames):
        m = run.obs_index[t]
        live.push(run.controls[t], run.local_maps[m] if m >= 0 else None, run.timestamps[t],
                  float(run.lattice_heading_array()[max(m, 0)]),
                  run.vo_failed is not None and bool(run.vo_failed[t]))
    s = live.stats()
    prediction = s.frame_latency[~np.asarray([m >= 0 for m in run.obs_index[1:]])]
    report = {
        "settings": {"course": args.course, "seed": args.seed, "frames": run.num_frames,
                     "config": str(args.config), "set": args.set,
                     "particles": args.particles, "map_shape": list(live.cfg.map_shape),
                     "store": live.cfg.store, "local_size": live.cfg.local_size,
                     "local_maps": s.updates},
        "first_frame_s": s.compile_seconds,
        "per_frame": _summary(s.frame_latency),
        "per_local_map_update": _summary(s.update_latency),
        "per_frame_without_local_map": _summary(prediction),
        "log_seconds": s.log_seconds, "compute_seconds": s.seconds,
        "realtime_factor": s.realtime_factor,
    }
    if run.ground_truth is not None:
        report["online_rms_m"] = rms_after_fit(live.path(), run.ground_truth)
    if args.batch:
        batch = slam.run_slam(run, config)
        report["batch_rms_m"] = rms_after_fit(batch.path, run.ground_truth)
        report["best_pose_equal"] = bool(np.array_equal(np.stack(live.best), batch.best_pose))
    report["environment"] = environment()
    text = json.dumps(report, indent=2)
    print(text)
    if args.out is not None:
        args.out.write_text(text + "\n")
    return report


if __name__ == "__main__":
    main()
