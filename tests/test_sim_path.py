"""The sim-path source: a trajectory file (TUM or KITTI poses) driven through a corridor world."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gslam_jax.config import Config
from gslam_jax.datasets.registry import Source, get_source
from gslam_jax.datasets.sim_path import read_path
from gslam_jax.errors import DatasetError
from gslam_jax.run import validate_run
from gslam_jax.sim.corridor import make_corridor_world
from gslam_jax.vo.geometry import CAM_TO_ROBOT_AXES, invert, make_transform

KITTI_00 = Path(__file__).resolve().parents[1] / "../shared/data/kitti-poses/00.txt"


def _planar(n: int = 400) -> np.ndarray:
    """A wavy synthetic path (x, y, yaw) that does not start at the origin or along x."""
    t = np.linspace(0.0, 60.0, n)
    x, y = 5.0 + t, -3.0 + 4.0 * np.sin(t / 8.0)
    yaw = np.arctan2(np.gradient(y), np.gradient(x)) + 0.3
    c, s = np.cos(0.3), np.sin(0.3)
    return np.stack([c * x - s * y, s * x + c * y, yaw], axis=1)


def _write_tum(path: Path, poses: np.ndarray) -> Path:
    yaw = poses[:, 2]
    rows = [f"{0.1 * k:.3f} {x:.9f} {y:.9f} 0 0 0 {np.sin(a / 2):.12f} {np.cos(a / 2):.12f}"
            for k, (x, y, a) in enumerate(zip(poses[:, 0], poses[:, 1], yaw))]
    path.write_text("# time x y z qx qy qz qw\n" + "\n".join(rows) + "\n")
    return path


def _write_kitti(path: Path, poses: np.ndarray, with_time: bool) -> Path:
    """Camera-to-world 3x4 matrices (camera x right, y down, z forward) of the robot poses."""
    t_rc = make_transform(CAM_TO_ROBOT_AXES, [0.0, 0.0, 0.0])
    rows = []
    for k, (x, y, a) in enumerate(poses):
        t_wr = make_transform([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]],
                              [x, y, 0.0])
        cam = (invert(t_rc) @ t_wr @ t_rc)[:3].ravel()
        stamp = [f"{0.1 * k:.3f}"] if with_time else []
        rows.append(" ".join(stamp + [f"{v:.12e}" for v in cam]))
    path.write_text("\n".join(rows) + "\n")
    return path


def _polyline_distance(points: np.ndarray, line: np.ndarray) -> np.ndarray:
    """Distance of each point to the polyline ``line`` (exact, segment by segment)."""
    a, b = line[:-1], line[1:]
    ab = b - a
    t = np.clip(((points[:, None] - a[None]) * ab[None]).sum(-1)
                / np.maximum((ab * ab).sum(-1), 1e-12)[None], 0.0, 1.0)
    closest = a[None] + t[..., None] * ab[None]
    return np.sqrt(((points[:, None] - closest) ** 2).sum(-1)).min(1)


def test_kitti_and_tum_files_give_the_same_planar_path(tmp_path) -> None:
    poses = _planar()
    tum = read_path(_write_tum(tmp_path / "p.tum", poses))
    k12 = read_path(_write_kitti(tmp_path / "p12.txt", poses, with_time=False))
    k13 = read_path(_write_kitti(tmp_path / "p13.txt", poses, with_time=True))
    assert (tum.format, k12.format, k13.format) == ("TUM", "KITTI", "KITTI")
    assert k12.times is None and np.allclose(k13.times, tum.times)
    np.testing.assert_allclose(k12.poses, tum.poses, atol=1e-7)
    np.testing.assert_allclose(k13.poses, tum.poses, atol=1e-7)
    # independently: the path in the frame of its first pose
    x0, y0, a0 = poses[0]
    c, s = np.cos(a0), np.sin(a0)
    dx, dy = poses[:, 0] - x0, poses[:, 1] - y0
    want = np.stack([c * dx + s * dy, -s * dx + c * dy, poses[:, 2] - a0], axis=1)
    np.testing.assert_allclose(tum.poses, want, atol=1e-7)


@pytest.mark.parametrize("text, where", [
    ("0 0 0 0 0 0 0 1\n0.1 1 0 0 0 0 0 1\n0.2 2 0 abc 0 0 0 1\n", ":3: 'abc' is not a number"),
    ("0 0 0 0 0 0 0 1\n0.1 1 0 0 0 0 1\n", ":2: 7 numbers, but 8 on line 1"),
    ("# header\n0 0 0 0 0\n", ":2: 5 numbers a line"),
    ("0 0 0 0 0 0 0 1\n0.1 1 0 0 0 0 0 0\n", ":2: quaternion of zero length"),
    ("0 0 0 0 0 0 0 1\n0.1 1 0 0 0 0 0 nan\n", ":2: non-finite number"),
])
def test_malformed_lines_are_named(tmp_path, text, where) -> None:
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(DatasetError, match=f"bad.txt{where}"):
        read_path(path)
    with pytest.raises(DatasetError, match="no such trajectory file"):
        read_path(tmp_path / "missing.txt")


def test_a_tum_loop_loads_into_a_run_along_the_file(tmp_path) -> None:
    """A 40 m circle (every 0.5 m) through the registry: the ground truth follows the file."""
    r = 40.0 / (2 * np.pi)
    phi = np.linspace(0.0, 2 * np.pi, 81)
    poses = np.stack([r * np.sin(phi), r * (1 - np.cos(phi)), phi], axis=1)
    path = _write_tum(tmp_path / "circle.tum", poses)
    loaded = get_source("sim-path").load(Source(source="sim-path", path=path, seed=1),
                                         Config(), None)
    run, info = loaded.run, loaded.sim_info
    validate_run(run)
    gt = run.ground_truth
    assert run.num_local_maps >= 10 and np.isfinite(run.controls).all()
    assert np.abs(_polyline_distance(gt[:, :2], poses[:, :2])).max() < 0.03
    # the whole loop is driven, heading along the path, and back at the start
    np.testing.assert_allclose(gt[-1, :2], gt[0, :2], atol=0.03)
    assert abs(gt[0, 2]) < 0.05 and abs(gt[-1, 2] - 2 * np.pi) < 0.05
    step = np.hypot(*np.diff(gt[:, :2], axis=0).T)
    assert 39.5 < step.sum() < 40.5 and step.max() <= 0.8 / 5 + 1e-9
    moving = step > 0.05
    along = np.arctan2(*np.diff(gt[:, :2], axis=0)[moving][:, ::-1].T)
    assert np.abs(np.angle(np.exp(1j * (along - gt[1:, 2][moving])))).max() < 0.05
    assert info.world.kind == "mars-yard" and info.points_per_frame > 1000
    # a Table I course's name picks its world kind
    arroyo = get_source("sim-path").load(Source(source="sim-path", path=path, course="arroyo-a",
                                                max_frames=30), Config(), None)
    assert arroyo.sim_info.world.kind == "arroyo" and arroyo.run.num_frames == 30


def test_corridor_world_memory_grows_with_length_not_area() -> None:
    """Diagonal straight paths: the world's bytes are linear in the length and far below the
    dense raster of the bounding box; a prefix's world holds the same tiles."""
    def world(length: float, driven: float | None = None):
        d = np.linspace(0.0, length, 200)[:, None] * np.array([[np.sqrt(0.5), np.sqrt(0.5)]])
        part = None if driven is None else d[d[:, 0] <= driven * np.sqrt(0.5) + 1e-9]
        return make_corridor_world("maze", 3, d, driven=part, half_width=12.0)

    short, long = world(150.0), world(300.0)
    assert 1.8 < long.nbytes / short.nbytes < 2.2
    dense = long.shape[0] * long.shape[1] * 13  # the bounding box as one raster
    assert long.nbytes < dense / 5
    per_m = long.nbytes / 300.0
    assert per_m < 2 * (24.0 + 2 * 6.4) * 400 * 13  # corridor and tile rims, 13 bytes a pixel
    # linear: a 2 km path would need about 2000 per_m bytes (tiles only, no content drawn)
    from gslam_jax.sim.tiled_world import corridor_tiles
    d = np.linspace(0.0, 2000.0, 50)[:, None] * np.array([[np.sqrt(0.5), np.sqrt(0.5)]])
    tiles = corridor_tiles(d, 12.0, 6.4)
    assert abs(len(tiles) * 128 * 128 * 13 / 2000.0 / per_m - 1.0) < 0.15
    # the world of a prefix: same content in the tiles both have
    prefix = world(300.0, driven=100.0)
    assert 0 < prefix.slots < long.slots
    for a, b in np.argwhere(prefix.tiles > 0):
        xa = prefix.origin[0] / 6.4 + a - long.origin[0] / 6.4
        xb = prefix.origin[1] / 6.4 + b - long.origin[1] / 6.4
        slot_long = long.tiles[int(round(xa)), int(round(xb))]
        for name in ("ground", "height", "rough", "material"):
            np.testing.assert_array_equal(getattr(prefix, name)[prefix.tiles[a, b]],
                                          getattr(long, name)[slot_long], err_msg=name)


def test_the_window_agrees_with_the_tiles() -> None:
    path = np.array([[0.0, 0.0], [30.0, 5.0], [40.0, 30.0]])
    w = make_corridor_world("arroyo", 0, path, half_width=11.0)
    local = w.local(30.0, 5.0, 10.2)
    assert local is w.local(30.1, 5.1, 10.2)  # kept while the robot stays in its tile
    i, j = np.meshgrid(np.arange(local.shape[0]), np.arange(local.shape[1]), indexing="ij")
    x = local.origin[0] + (i + 0.5) * w.resolution
    y = local.origin[1] + (j + 0.5) * w.resolution
    near = np.hypot(x - 30.0, y - 5.0) <= 10.2
    gi, gj = w.cell_of(np.stack([x[near], y[near]], -1))
    flat = w.flat_index(gi, gj)
    for name in ("ground", "height", "rough", "canopy_lo", "material"):
        np.testing.assert_array_equal(getattr(local, name)[near], getattr(w, name).ravel()[flat],
                                      err_msg=name)
    assert w.has_canopy and (w.tiles > 0).sum() == w.slots - 1


def test_kitti_00_first_frames() -> None:
    if not KITTI_00.is_file():
        pytest.skip(f"{KITTI_00} is absent (the KITTI pose files of ../shared/data)")
    loaded = get_source("sim-path").load(Source(source="sim-path", path=KITTI_00, seed=0,
                                                max_frames=300), Config(), None)
    run, info = loaded.run, loaded.sim_info
    validate_run(run)
    assert run.num_frames == 300 and run.num_local_maps >= 10
    assert np.isfinite(run.controls).all() and np.isfinite(run.ground_truth).all()
    assert info.course.length > 3500 and info.world.nbytes < 100e6
