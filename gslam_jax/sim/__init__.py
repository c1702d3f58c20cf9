"""Simulated off-road worlds and courses with ground truth (paper section 7).

courses.py      the Table I courses (seeded smooth paths of the paper's lengths)
world.py        the raster world and the shapes that populate it
environments.py the three environments: mars-yard, arroyo, maze
trajectory.py   speed profile and ground-truth poses at the frame rate
sensor.py       the stereo point sensor (ray casting, range^2 noise, dropouts, range gate)
vonoise.py      VO increments with eqs. 1-3 noise, slow bias and failures (true params kept)
corridor.py     tiled worlds only in a corridor around a long path (kilometres in memory)

``gslam_jax.datasets.sim.simulate_run`` assembles them into a ``Run``.
"""

from gslam_jax.sim.courses import COURSES, Course, CourseSpec, course_names, make_course
from gslam_jax.sim.environments import WORLD_KINDS, make_world, world_for_course
from gslam_jax.sim.sensor import PointSensor, SensorParams, depth_noise_std
from gslam_jax.sim.trajectory import DriveParams, Trajectory, drive
from gslam_jax.sim.vonoise import VO_PROFILES, VONoiseDraw, VONoiseParams, apply_vo_noise, true_increments
from gslam_jax.sim.world import Material, World

__all__ = ["COURSES", "Course", "CourseSpec", "course_names", "make_course", "WORLD_KINDS",
           "make_world", "world_for_course", "PointSensor", "SensorParams", "depth_noise_std",
           "DriveParams", "Trajectory", "drive", "VO_PROFILES", "VONoiseDraw", "VONoiseParams",
           "apply_vo_noise", "true_increments", "Material", "World"]
