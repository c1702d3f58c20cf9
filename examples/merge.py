"""Merge: the same terrain driven twice (another VO and sensor noise, B in its own frame),
each run mapped, B's map aligned in A's by the gamma likelihood and the two maps merged.

    python examples/merge.py            # GSLAM_EXAMPLE_FRAMES=300 by default
"""

import math
import os

import numpy as np

import gslam_jax

frames = int(os.environ.get("GSLAM_EXAMPLE_FRAMES", "300"))
config = gslam_jax.parse_config({"filter": {"particles": 16}})

run_a, _ = gslam_jax.simulate_run("mars-yard-a", seed=0, max_frames=frames)
run_b, _ = gslam_jax.simulate_run("mars-yard-a", seed=0, max_frames=frames, noise_seed=1)
truth = np.asarray(run_b.initial_pose, float)  # B's frame in A's (A runs in the world frame)
run_b = run_b._replace(initial_pose=np.zeros(3))  # B knows nothing of A: it starts at its origin

grid_a = gslam_jax.run_slam(run_a, config).grid
grid_b = gslam_jax.run_slam(run_b, config).grid

# B's frame in A's by align_maps (AlignmentRefused when the match is weak or ambiguous), then
# B's statistics added into A's frame (eq. 14).
merged = gslam_jax.merge_maps([grid_a, grid_b])
al = merged.alignments[1]
x, y, th = al.pose
std = np.sqrt(np.diag(al.covariance))
print(f"B's frame in A's: ({x:.3f} m, {y:.3f} m, {math.degrees(th):.2f} deg) "
      f"+- ({std[0]:.3f} m, {std[1]:.3f} m, {math.degrees(std[2]):.2f} deg), z {al.z:.1f}")
print(f"truth:            ({truth[0]:.3f} m, {truth[1]:.3f} m, "
      f"{math.degrees(truth[2]):.2f} deg)")
print(f"alignment error: {math.hypot(x - truth[0], y - truth[1]):.3f} m, "
      f"{abs(math.degrees(math.remainder(th - truth[2], 2 * math.pi))):.2f} deg")
print(f"merged map: {int(merged.grid.known.sum())} known cells "
      f"(A {int(grid_a.known.sum())}, B {int(grid_b.known.sum())})")
