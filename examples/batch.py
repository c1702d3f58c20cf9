"""Batch: a source of frames -> a config -> run_slam -> NumPy arrays.

    python examples/batch.py            # GSLAM_EXAMPLE_FRAMES=200 by default
"""

import os

import numpy as np

import gslam_jax

frames = int(os.environ.get("GSLAM_EXAMPLE_FRAMES", "200"))

# 1. The settings: the defaults with fewer particles (a TOML file: gslam_jax.load_config(path)).
config = gslam_jax.parse_config({"filter": {"particles": 16}})

# 2. The frames: any registered source (here the simulator; KITTI: Source(source="kitti",
#    path=..., sequence="00")), loaded into a Run of VO controls and local maps.
loaded = gslam_jax.load_source(gslam_jax.Source(source="sim", course="mars-yard-a", seed=0,
                                      max_frames=frames), config)
run = loaded.run
print(f"loaded {loaded.description}: {run.num_frames} frames, {run.num_local_maps} local maps")

# 3. The filter over the whole run.
result = gslam_jax.run_slam(run, config)

# 4. Arrays: the reported path [T, 3], the VO path, the map (a GridMap).
path, truth = result.path, run.ground_truth
err = np.hypot(*(path[:, :2] - truth[:, :2]).T)
vo_err = np.hypot(*(result.vo_path[:, :2] - truth[:, :2]).T)
print(f"final position error: SLAM {err[-1]:.3f} m, VO only {vo_err[-1]:.3f} m")
grid = result.grid
print(f"map: {grid.shape[0]} x {grid.shape[1]} cells of {grid.resolution} m, "
      f"{int(grid.known.sum())} known")
