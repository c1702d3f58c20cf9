"""Your own stereo rig: a folder of image pairs, a calibration and the camera mount -> a run.

Here the "rig" is simulated: one forward-looking stereo camera, 1.2 m up and pitched 20 degrees
down, driven 14 m along an S-curve through a Mars Yard world. The script writes what a real
rig's log would be, in the layout of ``--source stereo`` (docs/formats.md), then runs
Gamma-SLAM on it and prints the RMS against the ground truth it wrote:

    DIR/left/000000.png ...    DIR/right/000000.png ...    (rectified here: D = 0, R = I)
    DIR/calib.yaml             K, D, R, P per camera (ROS camera_info names)
    DIR/times.txt              one time a pair, seconds
    DIR/odometry.txt           wheel odometry, TUM (here the simulator's noisy odometry)
    DIR/groundtruth.txt        TUM, for scoring only
    DIR/rig.toml               the config: [rig] mount, fewer particles

The same from the command line, once the folder exists:

    gslam run --source stereo --path DIR --config DIR/rig.toml

    python examples/own_rig.py [DIR]      # GSLAM_EXAMPLE_FRAMES: the first frames only
"""

import os
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

import gslam_jax
from gslam_jax.datasets.sim import drive_course
from gslam_jax.evaluation.metrics import rms_after_fit
from gslam_jax.io import write_tum
from gslam_jax.sim.courses import course_from_path
from gslam_jax.sim.environments import world_for_course
from gslam_jax.sim.render import RenderParams, StereoRenderer
from gslam_jax.sim.trajectory import DriveParams
from gslam_jax.sim.vonoise import VO_PROFILES

frames = int(os.environ.get("GSLAM_EXAMPLE_FRAMES", "0")) or None
folder = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp(prefix="own_rig_"))
HEIGHT, PITCH = 1.2, 20.0  # metres above the ground, degrees nose down

# 1. Record a log: drive an S-curve at 2.5 frames a second and render the camera's pairs at
#    the true poses (320 x 240 px, 70 degrees wide).
s = np.linspace(0.0, 14.0, 57)
course = course_from_path(np.column_stack([s, 1.5 * np.sin(s / 3.0)]), "s-curve", "mars-yard",
                          "a 14 m S-curve")
odo = drive_course(course, 0, VO_PROFILES["mars-yard-a"], max_frames=frames,
                   drive_params=DriveParams(rate_hz=2.5, max_speed=1.0, max_accel=0.6,
                                            start_dwell=0.4, survey_dwell=0.4))
truth, times = odo.trajectory.poses, odo.trajectory.timestamps
render = RenderParams(width=320, height=240, focal_px=230.0, camera_height=HEIGHT,
                      camera_pitch=float(np.deg2rad(PITCH)), camera_yaw=0.0, supersample=1.0,
                      max_distance=16.0, fog_start=11.0)
renderer = StereoRenderer(world_for_course(course, 0), render, seed=0)
rng = np.random.default_rng(0)
for side in ("left", "right"):
    (folder / side).mkdir(parents=True, exist_ok=True)
for t, pose in enumerate(truth):
    left, right = renderer.camera_poses(pose)[0]  # the first (here forward-looking) pair
    cv2.imwrite(str(folder / "left" / f"{t:06d}.png"), renderer.render_view(left, rng))
    cv2.imwrite(str(folder / "right" / f"{t:06d}.png"), renderer.render_view(right, rng))

# 2. The calibration, as ROS camera_calibration writes it (both cameras share K here).
rig = renderer.rig
k = rig.k
with open(folder / "calib.yaml", "w") as f:
    for side, shift in (("left", 0.0), ("right", -rig.fx * rig.baseline)):
        p = np.hstack([k, [[shift], [0.0], [0.0]]])
        f.write(f"{side}:\n  image_width: {rig.size[0]}\n  image_height: {rig.size[1]}\n"
                f"  distortion_model: plumb_bob\n"
                f"  camera_matrix: {{rows: 3, cols: 3, data: {k.ravel().tolist()}}}\n"
                f"  distortion_coefficients: {{rows: 1, cols: 5, data: [0, 0, 0, 0, 0]}}\n"
                f"  rectification_matrix: {{rows: 3, cols: 3, data: [1, 0, 0, 0, 1, 0, 0, 0, 1]}}\n"
                f"  projection_matrix: {{rows: 3, cols: 4, data: {p.ravel().tolist()}}}\n")

# 3. Times, wheel odometry and ground truth (TUM: time x y z qx qy qz qw).
np.savetxt(folder / "times.txt", times, fmt="%.6f")
write_tum(folder / "odometry.txt", times, odo.vo_poses())
write_tum(folder / "groundtruth.txt", times, truth)

# 4. The config: where the left camera sits on the robot. The renderer's left camera is half
#    the 12 cm baseline left of the robot's centre line.
(folder / "rig.toml").write_text(
    f"[rig]\nheight = {HEIGHT}\npitch = {PITCH}\nlateral = {render.baseline / 2}\n\n"
    "[filter]\nparticles = 32\n")
print(f"wrote {len(truth)} stereo pairs, calib.yaml, times, odometry, ground truth and rig.toml "
      f"to {folder}")

# 5. Run it, as `gslam run --source stereo --path DIR --config DIR/rig.toml` would.
config = gslam_jax.load_config(folder / "rig.toml")
loaded = gslam_jax.load_source(gslam_jax.Source(source="stereo", path=folder), config)
result = gslam_jax.run_slam(loaded.run, config)
gt = loaded.run.ground_truth
print(f"RMS against groundtruth.txt: VO only {rms_after_fit(result.vo_path, gt):.3f} m, "
      f"Gamma-SLAM {rms_after_fit(result.path, gt):.3f} m "
      f"({loaded.run.num_local_maps} local maps)")
