"""trajectory_kitti.txt in KITTI's camera frame: KITTI's tools compare it with poses/NN.txt
without an alignment; the robot-frame path keeps its own file."""

from __future__ import annotations

import contextlib
import io
import shutil
from pathlib import Path

import numpy as np
import pytest

from gslam_jax.app.cli import main
from gslam_jax.datasets.kitti import KittiFrame, KittiParams, camera_poses, robot_from_camera

SRC = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti-stereo-51"


def _yaw_pose(x: float, y: float, th: float) -> np.ndarray:
    out = np.eye(4)
    out[:2, :2] = [[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]]
    out[:2, 3] = x, y
    return out


def _kitti_camera(x: float, y: float, th: float) -> np.ndarray:
    """KITTI's camera 0 (x right, y down, z forward) of a level car at planar robot pose
    (x forward, y left, heading th to the left), world = the camera at (0, 0, 0): turning left
    is a rotation by -th about the camera's y axis (down); forward is +z, left is -x."""
    c, s = np.cos(th), np.sin(th)
    out = np.eye(4)
    out[:3, :3] = [[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]]
    out[:3, 3] = -y, 0.0, x
    return out


def test_camera_poses_are_kittis_convention_written_out():
    rng = np.random.default_rng(3)
    path = np.column_stack([np.cumsum(rng.uniform(0, 2, 20)), rng.normal(0, 3, 20),
                            rng.uniform(-np.pi, np.pi, 20)])
    path[0] = 0.0
    frame = KittiFrame(robot_from_camera(KittiParams(camera_height=1.65)), np.eye(4))
    got = camera_poses(path, np.zeros(3), frame)
    want = np.stack([_kitti_camera(*p) for p in path])
    np.testing.assert_allclose(got, want, atol=1e-12)
    # A clip starting later in the sequence: its first pose's frame, as in poses/NN.txt; a
    # start pose elsewhere (a prior map's frame) is taken out first.
    first = _kitti_camera(40.0, -7.0, 0.8)
    first[1, 3] = 2.5  # a hill: the first camera need not be level at height 0
    start = np.array([5.0, -2.0, 1.1])
    moved = np.stack([_yaw_pose(*start) @ _yaw_pose(*p) for p in path])
    moved2d = np.column_stack([moved[:, 0, 3], moved[:, 1, 3],
                               np.arctan2(moved[:, 1, 0], moved[:, 0, 0])])
    got = camera_poses(moved2d, start, KittiFrame(frame.t_robot_cam, first))
    np.testing.assert_allclose(got, first @ want, atol=1e-9)


def test_camera_poses_carry_the_vos_height_and_tilt():
    """With ``off_plane`` of 6-DoF robot poses W_t, the planar path of those poses turns back
    into exactly the cameras inv(T_rc) W_t T_rc (world = the first camera): the height, roll and
    pitch the planar path lacks are W_t's."""
    from scipy.spatial.transform import Rotation

    from gslam_jax.datasets.kitti import off_plane

    rng = np.random.default_rng(5)
    n = 12
    world = np.tile(np.eye(4), (n, 1, 1))
    world[:, :3, :3] = Rotation.from_euler(
        "zyx", np.column_stack([rng.uniform(-3, 3, n), rng.normal(0, 0.05, n),
                                rng.normal(0, 0.05, n)])).as_matrix()
    world[:, :3, 3] = rng.normal(0, [20, 20, 1], (n, 3))
    yaw = np.arctan2(world[:, 1, 0], world[:, 0, 0])
    path = np.column_stack([world[:, 0, 3], world[:, 1, 3], yaw])
    t_rc = robot_from_camera(KittiParams(camera_height=1.65))
    got = camera_poses(path, np.zeros(3), KittiFrame(t_rc, np.eye(4), off_plane(world)))
    want = np.linalg.inv(t_rc) @ world @ t_rc
    np.testing.assert_allclose(got, want, atol=1e-9)


@pytest.fixture()
def kitti_clip(tmp_path: Path) -> Path:
    """The first 6 real frames in a KITTI layout (the whole poses file, as KITTI ships it)."""
    if not (SRC / "sequences" / "seq1").is_dir():
        pytest.skip(f"real KITTI frames not found at {SRC} (see shared/data/README.md)")
    seq = tmp_path / "kitti" / "sequences" / "seq1"
    for cam in ("image_0", "image_1"):
        (seq / cam).mkdir(parents=True)
        for t in range(6):
            shutil.copy(SRC / "sequences" / "seq1" / cam / f"{t:06d}.png", seq / cam)
    shutil.copy(SRC / "sequences" / "seq1" / "calib.txt", seq)
    shutil.copytree(SRC / "poses", tmp_path / "kitti" / "poses")
    return tmp_path / "kitti"


def test_a_kitti_run_writes_its_path_in_kittis_camera_frame(kitti_clip, tmp_path):
    out = tmp_path / "out"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["run", "--source", "kitti", "--path", str(kitti_clip), "--out", str(out),
                     "--set", "filter.particles=4"]) == 0
    est = np.loadtxt(out / "trajectory_kitti.txt").reshape(-1, 3, 4)
    truth = np.loadtxt(kitti_clip / "poses" / "seq1.txt").reshape(-1, 3, 4)[:len(est)]
    assert len(est) == 6 and truth[-1, 2, 3] > 5.0  # the car drove over 5 m along camera z
    # Read as evo_ape kitti reads them, no alignment: on the ground plane (x, z) the estimate
    # lies on the truth; the height (y, down) is the VO's, so it follows the road's climb (14 cm
    # over these 6.6 m) to the VO's own error
    ground = np.linalg.norm((est - truth)[:, [0, 2], 3], axis=1)
    assert ground.max() < 0.15, ground
    assert truth[0, 1, 3] - truth[-1, 1, 3] > 0.1  # the road climbs
    climb = np.abs(truth[:, 1, 3] - truth[0, 1, 3])
    height_error = np.abs(est[:, 1, 3] - truth[:, 1, 3])
    assert (height_error <= climb / 3 + 0.01).all(), (height_error, climb)
    assert np.degrees(_angle(est, truth)).max() < 3.0  # the filter's heading, within degrees
    # ... while the robot-frame path (x forward, y left, z up) is metres off
    robot = np.loadtxt(out / "trajectory_robot_kitti.txt").reshape(-1, 3, 4)
    assert np.linalg.norm((robot - truth)[-1, :, 3]) > 5.0


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[T] angles (radians) of the rotations between two [T, 3, 4] pose lists."""
    trace = np.einsum("tij,tij->t", a[:, :, :3], b[:, :, :3])
    return np.arccos(np.clip((trace - 1) / 2, -1, 1))


def _umeyama_rms(est: np.ndarray, ref: np.ndarray) -> float:
    """RMS of the positions [N, 3] after the SE(3) least-squares fit of est onto ref (Umeyama
    1991, no scale: what ``evo_ape -a`` reports as rmse)."""
    mu_e, mu_r = est.mean(0), ref.mean(0)
    cov = (ref - mu_r).T @ (est - mu_e) / len(est)
    u, _, vt = np.linalg.svd(cov)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u) * np.linalg.det(vt))])
    rot = u @ d @ vt
    moved = (est - mu_e) @ rot.T + mu_r
    return float(np.sqrt(np.mean(np.sum((moved - ref) ** 2, axis=1))))


def test_evo_on_the_tum_files_gives_the_summarys_rms(kitti_clip, tmp_path):
    """docs/formats.md: ``evo_ape tum ground_truth_tum.txt trajectory_tum.txt -a`` gives
    summary.json's slam_rms_m (and vo_tum.txt its vo_rms_m): both files are planar (z = 0), so
    evo's 3-D fit is the paper's 2-D fit. Computed here by an SE(3) fit of the files' columns."""
    import json

    out = tmp_path / "out"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["run", "--source", "kitti", "--path", str(kitti_clip), "--out", str(out),
                     "--set", "filter.particles=4"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    truth = np.loadtxt(out / "ground_truth_tum.txt")
    for name, key in (("trajectory_tum.txt", "slam_rms_m"), ("vo_tum.txt", "vo_rms_m")):
        est = np.loadtxt(out / name)
        np.testing.assert_array_equal(est[:, 0], truth[:, 0])  # same stamps: evo pairs them
        assert np.all(est[:, 3] == 0) and np.all(truth[:, 3] == 0)
        assert _umeyama_rms(est[:, 1:4], truth[:, 1:4]) == pytest.approx(summary[key],
                                                                          rel=1e-5, abs=1e-6)
