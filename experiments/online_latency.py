"""Latency of the live API (``gslam_jax.Online``): a simulated course replayed frame by frame,
the wall time of every push (a frame with or without a local map) after the first (which
compiles), and the real-time factor (seconds of log per second of filter compute).

    python -m experiments.online_latency --frames 600 --particles 100

Prints a JSON report with the machine and versions (``machine.environment``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from gslam_jax.config import parse_config
from gslam_jax.datasets.sim import simulate_run
from gslam_jax.machine import environment
from gslam_jax.online import Online
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
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--particles", type=int, default=100)
    ap.add_argument("--size", type=float, default=100.0,
                    help="side in metres of the square map around the start")
    ap.add_argument("--store", default="dense", help="[map] store")
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON report here")
    args = ap.parse_args(argv)

    config = parse_config({"filter": {"particles": args.particles},
                           "map": {"store": args.store}})
    run, _ = simulate_run(args.course, seed=0, params=localmap_params(config),
                          max_frames=args.frames)
    live = Online(config, args.size, start_pose=run.start_pose())
    for t in range(run.num_frames):
        m = run.obs_index[t]
        live.push(run.controls[t], run.local_maps[m] if m >= 0 else None, run.timestamps[t])
    s = live.stats()
    prediction = s.frame_latency[~np.asarray([m >= 0 for m in run.obs_index[1:]])]
    report = {
        "settings": {"course": args.course, "frames": run.num_frames,
                     "particles": args.particles, "map_shape": list(live.cfg.map_shape),
                     "store": live.cfg.store, "local_size": live.cfg.local_size,
                     "local_maps": s.updates},
        "first_frame_s": s.compile_seconds,
        "per_frame": _summary(s.frame_latency),
        "per_local_map_update": _summary(s.update_latency),
        "per_frame_without_local_map": _summary(prediction),
        "log_seconds": s.log_seconds, "compute_seconds": s.seconds,
        "realtime_factor": s.realtime_factor,
        "environment": environment(),
    }
    text = json.dumps(report, indent=2)
    print(text)
    if args.out is not None:
        args.out.write_text(text + "\n")
    return report


if __name__ == "__main__":
    main()
