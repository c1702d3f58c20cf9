"""Simulated source along a given trajectory: a recorded path driven through a generated world.

``--source sim-path --path FILE`` reads a trajectory file and drives the simulator's robot
along it through a world of one of the off-road kinds, so that real path and loop geometry
(e.g. the KITTI drives of ``../shared/data/kitti-poses``) meet simulated sensing:

- the file is TUM (``time x y z qx qy qz qw``, robot axes: x forward, z up) or KITTI poses (12
  numbers, a 3x4 camera-to-world matrix, or the time and those 12; camera axes x right, y down,
  z forward), told apart by the number of columns; both become planar robot poses the way the
  KITTI adapter does it (robot axes, world = the first pose's frame, then x, y and yaw);
- the robot follows the path's tangent at its own speeds (``sim.trajectory``: the file's times
  are not used, and the source says so, ``path_notes``; a rover's speeds, not a car's, suit
  the simulated sensing), stopping only at the start and the end;
- the world kind is ``course`` when it names one (``sim.environments.WORLD_KINDS``) or that of
  the Table I course it names; the VO noise is that course's profile (for a bare kind, its
  first course's); terrain exists only in a corridor around the path (``sim.corridor``), so a
  path kilometres long fits in memory;
- sensing and local maps are those of ``simulate_run`` (``datasets.sim.sense_run``).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

from gslam_jax.config import Config, ConfigError
from gslam_jax.datasets.kitti import KittiParams
from gslam_jax.datasets.reading import pose_jump, quat_to_matrix, read_table
from gslam_jax.datasets.registry import DataSource, LoadedSource, Source
from gslam_jax.datasets.sim import Odometry, ProgressFn, SimInfo, drive_course, sense_run
from gslam_jax.errors import DatasetError
from gslam_jax.run import Run
from gslam_jax.sim.corridor import make_corridor_world
from gslam_jax.sim.courses import COURSES, course_from_path
from gslam_jax.sim.environments import WORLD_KINDS
from gslam_jax.sim.sensor import SensorParams
from gslam_jax.sim.trajectory import DriveParams
from gslam_jax.sim.vonoise import VO_PROFILES, VONoiseParams
from gslam_jax.vo.geometry import CAM_TO_ROBOT_AXES, invert, make_transform, pose_to_2d
from gslam_jax.vo.localmap import LocalMapParams, localmap_params

__all__ = ["PlanarPath", "read_path", "path_notes", "world_kind", "drive_path", "simulate_path"]

_KIND_COURSE = {"mars-yard": "mars-yard-a", "arroyo": "arroyo-a", "maze": "maze"}
_FORMATS = {8: "TUM", 12: "KITTI", 13: "KITTI"}


class PlanarPath(NamedTuple):
    """A trajectory file's poses in the plane: [N, 3] (x, y, yaw; yaw unwrapped), the first at
    the origin heading along x; the file's times [N] (None where it has none) and format;
    the file's line of each pose [N]."""

    poses: np.ndarray
    times: np.ndarray | None
    format: str
    lines: np.ndarray | None = None


def read_path(path: str | Path) -> PlanarPath:
    """The planar robot path of a TUM or KITTI pose file (see the module docstring).

    DatasetError naming the file (and line) for a missing file, a line that is not numbers or
    whose count differs from the first, a column count that is neither format, or a TUM
    quaternion of zero length.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: no such trajectory file")
    table = read_table(path, 1, at_least=True)
    cols = table.data.shape[1]
    if cols not in _FORMATS:
        raise DatasetError(f"{path}:{table.lines[0]}: {cols} numbers a line; a trajectory file "
                           "has 8 (TUM: time x y z qx qy qz qw), 12 (KITTI: a 3x4 pose) or 13 "
                           "(KITTI with the time first)")
    data = table.data
    poses = np.tile(np.eye(4), (len(data), 1, 1))
    if cols == 8:
        q = data[:, 4:8]
        norm = np.linalg.norm(q, axis=1)
        if not np.all(norm > 1e-9):
            bad = int(np.flatnonzero(~(norm > 1e-9))[0])
            raise DatasetError(f"{path}:{table.lines[bad]}: quaternion of zero length")
        poses[:, :3, :3] = quat_to_matrix(q, scalar_last=True)
        poses[:, :3, 3] = data[:, 1:4]
        times = data[:, 0].copy()
    else:
        # camera-to-world -> robot-to-world, as datasets.kitti does with its ground truth
        t_rc = make_transform(CAM_TO_ROBOT_AXES, [0.0, 0.0, KittiParams().camera_height])
        poses[:, :3, :] = data[:, -12:].reshape(-1, 3, 4)
        poses = t_rc @ poses @ invert(t_rc)
        times = data[:, 0].copy() if cols == 13 else None
    rel = invert(poses[0]) @ poses  # world = the first pose's frame
    planar = np.stack([pose_to_2d(p) for p in rel])
    planar[:, 2] = np.unwrap(planar[:, 2])
    return PlanarPath(planar, times, _FORMATS[cols], table.lines)


def world_kind(course: str) -> tuple[str, VONoiseParams]:
    """The world kind and VO noise profile ``course`` names: a world kind (its first Table I
    course's profile) or a Table I course (its kind and profile)."""
    if course in WORLD_KINDS:
        return course, VO_PROFILES[_KIND_COURSE[course]]
    if course in COURSES:
        return COURSES[course].kind, VO_PROFILES[course]
    raise ConfigError(f"unknown world {course!r} for a simulated path; use a world kind "
                      f"({', '.join(WORLD_KINDS)}) or a course ({', '.join(COURSES)})")


def drive_path(path: str | Path, seed: int = 0, course: str = "mars-yard", *,
               drive_params: DriveParams | None = None, vo_noise: VONoiseParams | None = None,
               max_frames: int | None = None) -> Odometry:
    """The odometry half of ``simulate_path`` (the same arguments, the same numbers): the
    ground truth at the frame rate and the VO increments drawn with ``vo_noise`` (default:
    the profile of ``course``), without the world and the sensor."""
    kind, profile = world_kind(course)
    planar = read_path(path)
    try:
        crs = course_from_path(planar.poses[:, :2], f"path {Path(path).name}", kind,
                               f"{planar.format} trajectory {path}", seed)
    except ValueError as e:
        raise DatasetError(f"{path}: {e}") from None
    return drive_course(crs, seed, vo_noise or profile, drive_params=drive_params,
                        max_frames=max_frames)


def simulate_path(path: str | Path, seed: int = 0, course: str = "mars-yard",
                  params: LocalMapParams | None = None, *, sensor: SensorParams | None = None,
                  drive_params: DriveParams | None = None, vo_noise: VONoiseParams | None = None,
                  max_frames: int | None = None, half_width: float | None = None,
                  progress: ProgressFn | None = None) -> tuple[Run, SimInfo]:
    """Drive the trajectory file ``path`` through a world picked by ``course`` (see
    ``world_kind``), seeded by ``seed``, as ``simulate_run`` drives a Table I course.

    vo_noise: defaults to the profile of ``course``. max_frames: the first frames only (the
    world then covers only the driven part; a truncated run is a prefix of the full one).
    half_width: metres of terrain either side of the path (default: the sensor's range + 2).
    """
    params = params or LocalMapParams()
    sensor = sensor or SensorParams(max_range=params.max_range)
    t0 = time.perf_counter()
    odo = drive_path(path, seed, course, drive_params=drive_params, vo_noise=vo_noise,
                     max_frames=max_frames)
    width = sensor.max_range + 2.0 if half_width is None else half_width
    world = make_corridor_world(world_kind(course)[0], seed, odo.course.path,
                                driven=odo.trajectory.poses[:, :2], half_width=width)
    timings = {"world_s": time.perf_counter() - t0}
    return sense_run(odo, world, seed, params, sensor, progress=progress, timings=timings,
                     t0=t0)


def path_notes(path: str | Path, planar: PlanarPath, drive_params: DriveParams | None = None
               ) -> list[str]:
    """What a user should know about how a trajectory file is driven: a jump far beyond the
    file's median step (``datasets.reading.pose_jump``), and, where the file has times, that the
    simulated robot keeps its own speeds instead (the file's duration and mean speed)."""
    notes = []
    jump = pose_jump(planar.poses[:, :2], planar.lines, path)
    if jump is not None:
        notes.append(jump)
    if planar.times is not None and len(planar.times) > 1:
        span = float(planar.times[-1] - planar.times[0])
        length = float(np.sum(np.hypot(*np.diff(planar.poses[:, :2], axis=0).T)))
        speed = f", {length / span:.2f} m/s on average" if span > 0 else ""
        top = (drive_params or DriveParams()).max_speed
        notes.append(f"{path}: the file's clock ({span:.1f} s for {length:.0f} m{speed}) is not "
                     f"used: the simulated robot drives the path at its own speeds (up to "
                     f"{top:g} m/s), so the run's times and its number of frames are its own")
    return notes


def _load(src: Source, config: Config, progress: ProgressFn | None = None) -> LoadedSource:
    for note in path_notes(src.path, read_path(src.path)):
        print(f"note: {note}")
    run, info = simulate_path(src.path, seed=src.sim_seed, course=src.course,
                              params=localmap_params(config), max_frames=src.max_frames,
                              progress=progress)
    return LoadedSource(run, f"simulated path {src.path} ({info.course.length:.0f} m, "
                             f"{info.world.kind} world, seed {src.sim_seed})", info)


SOURCE = DataSource(name="sim-path", help="a trajectory file driven through a simulated world "
                    "(--course picks the world kind and VO noise; point sensor)", load=_load,
                    simulated=True,
                    path="a trajectory file: TUM (time x y z qx qy qz qw) or KITTI poses (12 "
                    "numbers per line, or time + 12 as in ../shared/data/kitti-poses)")
