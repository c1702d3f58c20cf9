"""Live: gslam_jax.Online fed one frame at a time, as a robot would (here a simulated run
replayed frame by frame); the map is given an extent, since a live robot has no path yet.

    python examples/live.py             # GSLAM_EXAMPLE_FRAMES=200 by default
"""

import os

import numpy as np

import gslam_jax

frames = int(os.environ.get("GSLAM_EXAMPLE_FRAMES", "200"))
config = gslam_jax.parse_config({"filter": {"particles": 16}})

# A stand-in for the robot: a simulated run's VO controls and local maps, frame by frame.
run, _ = gslam_jax.simulate_run("mars-yard-a", seed=0, max_frames=frames)

# The map: a 60 m square around the start (the filter never resizes it; past its edge
# push() raises MapEdgeError). One jitted step per frame, compiled at the first.
slam = gslam_jax.Online(config, 60.0, start_pose=run.start_pose(), seed=0)
for t in range(run.num_frames):
    m = run.obs_index[t]
    local_map = run.local_maps[m] if m >= 0 else None  # [L, L, 3] (n, sum z, sum z^2) or None
    est = slam.push(run.controls[t], local_map, time_s=run.timestamps[t],
                    vo_failed=bool(run.vo_failed[t]))  # the wheel fallback's frame
    if t % 50 == 0 or t == run.num_frames - 1:
        err = np.hypot(*(est.pose[:2] - run.ground_truth[t, :2]))
        x, y, th = est.pose
        print(f"frame {t:4d}: pose ({x:.3f} m, {y:.3f} m, {th:.3f} rad)  error {err:.3f} m  "
              f"ESS {est.ess:.1f}")

particles = slam.particles()  # any time: poses [J, 3], weights [J]
grid = slam.map()             # any time: the best particle's GridMap
stats = slam.stats()
print(f"{len(particles.weight)} particles; map {grid.shape[0]} x {grid.shape[1]} cells, "
      f"{int(grid.known.sum())} known")
print(f"first frame {stats.compile_seconds:.2f} s (compilation); then "
      f"{1e3 * np.mean(stats.frame_latency):.2f} ms per frame, "
      f"{1e3 * np.mean(stats.update_latency):.2f} ms per local map; "
      f"real-time factor {stats.realtime_factor:.1f}")
