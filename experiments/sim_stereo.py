"""Rendered stereo vs the point sensor on a simulated course (issue 4, "On rendered simulated
stereo"): VO drift (final position error per distance travelled, start-anchored) and the
end-to-end Gamma-SLAM RMS (after the 2-D rigid fit, all frames) for both sources, same course,
same seed, same frames.

    python -m experiments.sim_stereo [--course mars-yard-a] [--seed 0] [--frames 400]
                                     [--particles 100] [--json out.json]

The point-sensor run's VO is the simulator's noise model (``sim.vonoise``, calibrated to Table I);
the rendered run's VO is the real OpenCV front-end on rendered images.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import cv2

from gslam_jax.config import Config
from gslam_jax.datasets.sim import simulate_run
from gslam_jax.datasets.sim_stereo import load_sim_stereo
from gslam_jax.driver import slam
from gslam_jax.driver.machine import environment
from gslam_jax.evaluation import metrics
from gslam_jax.vo.localmap import localmap_params


def _row(name: str, run, config: Config) -> dict:
    gt = run.ground_truth
    res = slam.run_slam(run, config)
    return {"source": name, "frames": run.num_frames, "distance_m": metrics.path_length(gt),
            "vo_drift_pct": 100 * metrics.drift_per_distance(run.vo_poses(), gt),
            "vo_rms_m": metrics.rms_after_fit(res.vo_path, gt),
            "slam_rms_m": metrics.rms_after_fit(res.best_path, gt),
            "local_maps": run.num_local_maps, "resamples": int(res.resampled.sum()),
            "filter_s": res.seconds + res.compile_seconds}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--course", default="mars-yard-a")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frames", type=int, default=400, help="course prefix (0: whole course)")
    ap.add_argument("--particles", type=int, default=100)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    config = Config()
    config = dataclasses.replace(config, filter=dataclasses.replace(config.filter,
                                                                    particles=args.particles))
    params = localmap_params(config, "stereo")
    frames = args.frames or None
    env = environment()
    print(f"# {env['date']} | {env['processor']} | {env['cpus']} cpus | jax {env['jax']} | "
          f"numpy {env['numpy']} | opencv {env['opencv']} | cv2 threads 1")
    t0 = time.perf_counter()
    run_s, info = load_sim_stereo(args.course, args.seed, params, frames,
                                  progress=lambda d, n: print(f"\r  rendering {d}/{n}", end="",
                                                              file=sys.stderr, flush=True))
    print(file=sys.stderr)
    print(info.text())
    run_p, _ = simulate_run(args.course, args.seed, params, max_frames=frames)
    rows = [_row("rendered stereo + OpenCV VO", run_s, config),
            _row("point sensor + simulated VO", run_p, config)]
    print(f"{args.course} seed {args.seed}, frames {run_s.num_frames} "
          f"({'whole course' if frames is None else 'course prefix'}), J = {args.particles}, {time.perf_counter() - t0:.0f} s total")
    print(f"{'source':<30} {'dist m':>7} {'VO drift %':>10} {'VO RMS m':>9} {'SLAM RMS m':>10} "
          f"{'maps':>5}")
    for r in rows:
        print(f"{r['source']:<30} {r['distance_m']:7.1f} {r['vo_drift_pct']:10.2f} "
              f"{r['vo_rms_m']:9.3f} {r['slam_rms_m']:10.3f} {r['local_maps']:5d}")
    if args.json:
        args.json.write_text(json.dumps({"environment": env, "course": args.course,
                                         "seed": args.seed, "rows": rows,
                                         "timings_s": info.timings}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
