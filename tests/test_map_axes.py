"""``[map] axes``: a map lattice turned in its frame (``GridMap.heading``), and the filter run
on the robot's start axes, whose result turns with the frame the run is given in and changes
in nothing else (the maze's walls showed that the frame's axes matter, docs/notebook/results.md)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from gslam_jax.config import Config
from gslam_jax.gridmap import (GridMap, add, known_cells, load_map, place, save_map, transform,
                               turn_poses)

RES = 0.25


def _grid(heading: float, seed: int = 0) -> GridMap:
    rng = np.random.default_rng(seed)
    k = rng.integers(0, 4, (7, 5)).astype(float)
    S = np.where(k > 0, rng.uniform(0.1, 1.0, k.shape), 0.0)
    return GridMap(k, S, (-0.8, 0.3), RES, heading)


def _centre(grid: GridMap, i: int, j: int) -> tuple[float, float]:
    """Cell (i, j)'s centre in the map's frame, written out by hand."""
    u = grid.origin[0] + (i + 0.5) * grid.resolution
    v = grid.origin[1] + (j + 0.5) * grid.resolution
    c, s = math.cos(grid.heading), math.sin(grid.heading)
    return c * u - s * v, s * u + c * v


def test_known_cells_and_transform_place_each_cell_by_the_lattice_heading() -> None:
    grid = _grid(0.7)
    centres, k, _ = known_cells(grid)
    expected = [_centre(grid, i, j) for i, j in zip(*np.nonzero(grid.k > 0))]
    np.testing.assert_allclose(centres, expected, atol=1e-12)
    for like_heading in (0.0, -0.4):
        like = GridMap(np.zeros((1, 1)), np.zeros((1, 1)), (0.1, -0.05), RES, like_heading)
        pose = np.array([1.3, -0.6, 0.25])
        moved = transform(grid, pose, like=like)
        assert moved.heading == like_heading
        # brute force: each known cell's centre carried by the pose, then into like's axes
        want = {}
        for i, j in zip(*np.nonzero(grid.k > 0)):
            x, y = _centre(grid, i, j)
            X = pose[0] + math.cos(pose[2]) * x - math.sin(pose[2]) * y
            Y = pose[1] + math.sin(pose[2]) * x + math.cos(pose[2]) * y
            c, s = math.cos(-like_heading), math.sin(-like_heading)
            u, v = c * X - s * Y, s * X + c * Y
            cell = (math.floor((u - like.origin[0]) / RES), math.floor((v - like.origin[1]) / RES))
            want[cell] = want.get(cell, 0.0) + grid.k[i, j]
        got = {}
        for i, j in zip(*np.nonzero(moved.k > 0)):
            cell = (round((moved.origin[0] - like.origin[0]) / RES) + i,
                    round((moved.origin[1] - like.origin[1]) / RES) + j)
            got[cell] = moved.k[i, j]
        assert got == pytest.approx(want)


def test_a_turned_lattice_is_saved_and_only_summed_with_its_own(tmp_path) -> None:
    grid = _grid(-1.1)
    save_map(tmp_path / "map.npz", grid)
    back = load_map(tmp_path / "map.npz")
    assert back.heading == pytest.approx(-1.1) and back.origin == grid.origin
    np.testing.assert_array_equal(back.k, grid.k)
    # a file written before the heading existed: the frame's axes
    np.savez(tmp_path / "old.npz", k=grid.k, S=grid.S, origin=np.array(grid.origin),
             resolution=RES)
    assert load_map(tmp_path / "old.npz").heading == 0.0
    assert add(grid, grid).heading == grid.heading
    assert place(grid, (-1.05, 0.05), (9, 7)).heading == grid.heading
    with pytest.raises(ValueError, match="do not share a lattice"):
        add(grid, grid._replace(heading=0.0))


def _maze_run(frames: int = 260):
    from gslam_jax.datasets.sim import simulate_run
    from gslam_jax.vo.localmap import LocalMapParams

    run, _ = simulate_run("maze", 0, LocalMapParams(resolution=0.16, max_range=6.0, travel=1.0),
                          max_frames=frames)
    return run


def _turned(run, degrees: float):
    """The same log in a frame turned by ``degrees`` about its start (as
    ``experiments.common.turned_run``, written out here)."""
    a = math.radians(degrees)
    start = run.start_pose()
    truth = turn_poses(run.ground_truth - np.array([start[0], start[1], 0.0]), a)
    truth[:, :2] += start[:2]
    return run._replace(initial_pose=start + np.array([0.0, 0.0, a]), ground_truth=truth)


def _config(axes: str) -> Config:
    c = Config()
    return dataclasses.replace(c, map=dataclasses.replace(c.map, axes=axes, margin=3.0),
                               filter=dataclasses.replace(c.filter, particles=16))


def test_on_the_start_axes_the_result_turns_with_the_frame_and_nothing_else() -> None:
    from gslam_jax.driver.slam import run_slam

    run = _maze_run()
    turn = 30.0
    start = run_slam(run, _config("start")), run_slam(_turned(run, turn), _config("start"))
    assert start[0].map_heading == pytest.approx(run.start_pose()[2])
    assert start[1].map_heading == pytest.approx(run.start_pose()[2] + math.radians(turn))
    np.testing.assert_array_equal(start[0].kmap, start[1].kmap)
    np.testing.assert_array_equal(start[0].smap, start[1].smap)
    for name in ("best_path", "mean_pose", "smoothed_path", "vo_path"):
        a, b = getattr(start[0], name), getattr(start[1], name)
        d = turn_poses(a, math.radians(turn)) - b
        d[:, 2] = np.angle(np.exp(1j * d[:, 2]))
        assert np.abs(d).max() < 1e-9, name
    # on the frame's axes the same turn gives another map: the property is not trivial
    frame = run_slam(_turned(run, turn), _config("frame"))
    assert frame.map_heading == 0.0
    assert frame.kmap.shape != start[1].kmap.shape or (frame.kmap != start[1].kmap).any()


def _local_maps(axes: str, turn: float):
    """Local maps on the map's lattice ("map") of one drive seen in a frame turned by ``turn``
    radians about its start: the same points, the VO poses turned."""
    from gslam_jax.vo.localmap import LocalMapParams, build_local_maps

    rng = np.random.default_rng(3)
    T = 40
    heading = 0.4 + np.cumsum(rng.normal(0.0, 0.03, T))
    xy = np.cumsum(0.3 * np.column_stack([np.cos(heading), np.sin(heading)]), axis=0)
    poses = turn_poses(np.column_stack([xy, heading]), turn)
    frames = [np.column_stack([rng.uniform(-3, 3, (200, 2)), rng.normal(0, 0.1, 200)])
              for _ in range(T)]
    params = LocalMapParams(resolution=0.2, max_range=3.0, travel=1.0, lattice="map", axes=axes)
    return build_local_maps(poses, iter(frames), params, poses[0]), poses


def test_a_map_lattice_on_the_start_axes_is_binned_alike_in_any_frame() -> None:
    """``[localmap] lattice = "map"`` with ``[map] axes = "start"``: each local map is binned on
    the robot's start axes, so a drive seen in a turned frame gives the same local maps; on the
    frame's axes it does not. ``map_axes.local_lattice_axes`` reads the axes back from a Run."""
    from gslam_jax.driver.map_axes import local_lattice_axes
    from gslam_jax.run import Run
    from gslam_jax.vo.geometry import increments_2d

    (a, _), (b, poses_b) = _local_maps("start", 0.0), _local_maps("start", 0.9)
    np.testing.assert_array_equal(a.obs_index, b.obs_index)
    np.testing.assert_allclose(a.local_maps, b.local_maps, atol=1e-9)
    np.testing.assert_allclose(a.lattice_headings, b.lattice_headings, atol=1e-9)
    (f0, _), (f1, _) = _local_maps("frame", 0.0), _local_maps("frame", 0.9)
    np.testing.assert_allclose(np.angle(np.exp(1j * (f1.lattice_headings - f0.lattice_headings))),
                               -0.9, atol=1e-9)
    assert not np.allclose(f0.local_maps, f1.local_maps)
    for maps, poses, axes in ((b, poses_b, poses_b[0, 2]), (f1, poses_b, 0.0)):
        controls = increments_2d(poses)
        run = Run(controls, maps.obs_index, maps.local_maps, 0.2, np.arange(len(poses)) * 0.1,
                  initial_pose=poses[0], lattice_headings=maps.lattice_headings)
        assert local_lattice_axes(run) == pytest.approx(axes, abs=1e-9)


def test_local_maps_binned_on_other_axes_than_the_map_are_named() -> None:
    """A Run whose "map" lattice lies on the frame's axes, filtered on the start axes (or the
    other way round), warns: each local cell would be placed by its centre."""
    import warnings

    from gslam_jax.driver.map_axes import LatticeWarning
    from gslam_jax.driver.slam import run_slam
    from gslam_jax.run import Run
    from gslam_jax.vo.geometry import increments_2d

    def run_of(axes: str) -> Run:
        maps, poses = _local_maps(axes, 0.9)
        return Run(increments_2d(poses), maps.obs_index, maps.local_maps, 0.2,
                   np.arange(len(poses)) * 0.1, initial_pose=poses[0],
                   lattice_headings=maps.lattice_headings)

    c = Config()
    for built, filtered, warns in (("frame", "start", True), ("start", "frame", True),
                                   ("start", "start", False), ("frame", "frame", False)):
        config = dataclasses.replace(
            c, map=dataclasses.replace(c.map, resolution=0.2, axes=filtered, margin=2.0),
            filter=dataclasses.replace(c.filter, particles=4))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            run_slam(run_of(built), config)
        named = [w for w in caught if issubclass(w.category, LatticeWarning)]
        assert bool(named) == warns, (built, filtered)


def test_a_turned_lattice_is_georeferenced_where_its_cells_lie() -> None:
    """The world file of a map on turned axes (``gps.lattice_rotation``) puts the top-left
    cell's centre where the GPS alignment (R, l) carries that cell's centre in the map's frame
    (``known_cells``)."""
    from gslam_jax.gps import lattice_rotation, world_file_params

    grid = _grid(0.8)
    a = 0.3
    R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    shift = np.array([500.0, -20.0])
    A, D, B, E, C, F = world_file_params(grid.origin, grid.resolution, grid.shape,
                                         lattice_rotation(R, grid.heading), shift)
    only = grid._replace(k=np.zeros(grid.shape), S=np.zeros(grid.shape))
    only.k[0, -1], only.S[0, -1] = 1.0, 1.0  # the top-left pixel: cell (0, ny - 1)
    centre = known_cells(only)[0][0]
    np.testing.assert_allclose([C, F], R @ centre + shift, atol=1e-9)
