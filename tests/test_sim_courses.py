"""Courses: Table I lengths, drivable speeds, survey stops, and paths clear of obstacles."""

from __future__ import annotations

import numpy as np
import pytest

from gslam_jax.sim import Material, course_names, drive, make_course, world_for_course
from gslam_jax.sim.world import path_clearance_mask

TABLE_I = {"mars-yard-a": 164.0, "mars-yard-b": 204.0, "arroyo-a": 335.0, "arroyo-b": 406.0,
           "maze": 543.0}
SOLID = [int(m) for m in (Material.ROCK, Material.POLE, Material.BIN, Material.BUILDING,
                          Material.BUSH, Material.TREE, Material.SCRUB)]


def test_the_five_courses_exist() -> None:
    assert sorted(course_names()) == sorted(TABLE_I)


@pytest.mark.parametrize("name", list(TABLE_I))
def test_course_length_and_driving(name: str) -> None:
    course = make_course(name, seed=3)
    assert course.length == pytest.approx(TABLE_I[name], rel=0.05)
    traj = drive(course)
    xy = traj.poses[:, :2]
    driven = np.hypot(*np.diff(xy, axis=0).T).sum()
    assert driven == pytest.approx(TABLE_I[name], rel=0.05)
    dt = np.diff(traj.timestamps)
    np.testing.assert_allclose(dt, 0.2)  # 5 Hz
    speed = np.hypot(*np.diff(xy, axis=0).T) / dt
    assert speed.max() <= 1.0
    # the path is smooth: no heading jumps between frames
    assert np.abs(np.diff(traj.poses[:, 2])).max() < 0.3
    # survey stops: stationary, first at the start, last at the end (a closed course)
    assert len(traj.survey_frames) >= 2
    for f in traj.survey_frames:
        assert np.hypot(*(xy[f] - xy[max(f - 1, 0)])) < 1e-6
    assert np.hypot(*(xy[-1] - xy[0])) < 3.0


@pytest.mark.parametrize("name", list(TABLE_I))
def test_path_keeps_clear_of_obstacles(name: str) -> None:
    course = make_course(name, seed=1)
    world = world_for_course(course, seed=1)
    footprint = path_clearance_mask(world, course.path, 0.4)  # robot half-width plus margin
    assert not np.isin(world.material[footprint], SOLID).any()
    tall = (world.height - world.ground)[footprint]
    assert tall.max() < 0.4  # grass at most


def test_unknown_course_lists_the_valid_ones() -> None:
    with pytest.raises(ValueError, match="mars-yard-a.*maze"):
        make_course("mars-yard-c")
