"""The generic stereo source (--source stereo): its layout, both calib.yaml forms, times, TUM
odometry and ground truth, named errors, and the same Run as the KITTI source on the KITTI
clip laid out as a stereo folder."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gslam_jax.config import Config, ConfigError, apply_overrides
from gslam_jax.datasets.calib_yaml import open_yaml
from gslam_jax.datasets.kitti import read_kitti_poses
from gslam_jax.datasets.mount import mount_matrix
from gslam_jax.datasets.registry import Source, get_source
from gslam_jax.datasets.stereo import (StereoParams, find_pairs, poses_at, read_calib_yaml,
                                       read_stereo_calib, read_tum_poses, stereo_frontend)
from gslam_jax.errors import DatasetError
from gslam_jax.vo.calib import CalibrationError, ImageError, RectifiedRig

KITTI = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "kitti-stereo-51"
SIZE = (320, 240)
K0 = np.array([[300.0, 0, 158], [0, 302, 121], [0, 0, 1]])
K1 = np.array([[305.0, 0, 162], [0, 301, 118], [0, 0, 1]])
D0 = np.array([-0.12, 0.03, 1e-3, -5e-4, 0.0])
D1 = np.array([-0.10, 0.02, -1e-3, 4e-4, 0.0])
R10 = cv2.Rodrigues(np.array([0.01, -0.02, 0.005]))[0]
T10 = np.array([-0.12, 0.003, 0.002])


def _flat(a: np.ndarray) -> str:
    return "[" + ", ".join(repr(float(v)) for v in np.ravel(a)) + "]"


def _ros_yaml(cams: list[tuple[np.ndarray, ...]], size=SIZE) -> str:
    """calib.yaml in the per-camera form with ROS camera_info names, written by hand."""
    out = []
    for side, (k, d, r, p) in zip(("left", "right"), cams):
        out += [f"{side}:", f"  image_width: {size[0]}", f"  image_height: {size[1]}",
                "  distortion_model: plumb_bob"]
        for name, a, (rows, cols) in (("camera_matrix", k, (3, 3)),
                                      ("distortion_coefficients", d, (1, len(d))),
                                      ("rectification_matrix", r, (3, 3)),
                                      ("projection_matrix", p, (3, 4))):
            out += [f"  {name}:", f"    rows: {rows}", f"    cols: {cols}",
                    f"    data: {_flat(a)}"]
    return "\n".join(out) + "\n"


def _rectification():
    r0, r1, p0, p1, *_ = cv2.stereoRectify(K0, D0, K1, D1, SIZE, R10, T10.reshape(3, 1),
                                           flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.0)
    return (K0, D0, r0, p0), (K1, D1, r1, p1)


def test_per_camera_ros_yaml_gives_the_rectification_written(tmp_path):
    left, right = _rectification()
    path = tmp_path / "calib.yaml"
    path.write_text(_ros_yaml([left, right]))
    rig = read_calib_yaml(path, SIZE)
    p0 = left[3]
    assert (rig.fx, rig.fy, rig.cx, rig.cy) == pytest.approx((p0[0, 0], p0[1, 1], p0[0, 2],
                                                              p0[1, 2]))
    assert rig.baseline == pytest.approx(np.linalg.norm(T10), rel=1e-6)
    assert np.allclose(rig.r_left, left[2])
    # the remap table sends rectified pixels to the raw pixels OpenCV's own tables do
    lx, ly = cv2.initUndistortRectifyMap(K0, D0, left[2], p0, SIZE, cv2.CV_32FC1)
    assert np.allclose(rig.maps[0], lx) and np.allclose(rig.maps[1], ly)


def test_opencv_stereo_extrinsic_yaml_agrees_with_the_per_camera_form(tmp_path):
    path = tmp_path / "calib.yaml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for name, value in (("K1", K0), ("D1", D0), ("K2", K1), ("D2", D1), ("R", R10),
                        ("T", T10.reshape(3, 1))):
        fs.write(name, value)
    fs.write("image_width", SIZE[0])
    fs.write("image_height", SIZE[1])
    fs.release()
    a = read_calib_yaml(path, SIZE)
    left, right = _rectification()
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "calib.yaml").write_text(_ros_yaml([left, right]))
    b = read_stereo_calib(tmp_path / "b", SIZE)
    assert (a.fx, a.cx, a.cy, a.baseline) == pytest.approx((b.fx, b.cx, b.cy, b.baseline))
    for m, n in zip(a.maps, b.maps):
        assert np.allclose(m, n, atol=1e-3)


def test_rectified_ros_yaml_needs_no_remap(tmp_path):
    k = np.array([[400.0, 0, 160], [0, 400, 120], [0, 0, 1]])
    p0 = np.hstack([k, np.zeros((3, 1))])
    p1 = p0.copy()
    p1[0, 3] = -400.0 * 0.3
    path = tmp_path / "calib.yaml"
    path.write_text(_ros_yaml([(k, np.zeros(5), np.eye(3), p0), (k, np.zeros(5), np.eye(3), p1)]))
    rig = read_calib_yaml(path, SIZE)
    assert rig.maps is None and rig.baseline == pytest.approx(0.3)


@pytest.mark.parametrize("edit, match", [
    (lambda t: t.replace("  projection_matrix:", "  projection_matrx:", 1), "'left.P'"),
    (lambda t: t.replace("data: [300.0", "data: [300.0, 1.0", 1), "'left.camera_matrix' has 10"),
    (lambda t: t.replace("image_width: 320", "image_width: 640", 1), "'left' image size 640x240"),
    (lambda t: t.replace("right:", "other:"), "missing map 'right'"),
    (lambda t: "camera: 1\n", "neither form"),
    (lambda t: t.replace("plumb_bob", "kannala", 1), "left: distortion_model 'kannala'"),
    (lambda t: "left: [\n", "not a readable YAML file"),
])
def test_calibration_errors_name_the_file_and_field(tmp_path, edit, match):
    path = tmp_path / "calib.yaml"
    path.write_text(edit(_ros_yaml(list(_rectification()))))
    with pytest.raises(CalibrationError, match=rf"calib.yaml.*{match}"):
        read_calib_yaml(path, SIZE)


def test_calibration_file_choice(tmp_path):
    with pytest.raises(CalibrationError, match=r"calib.yaml: calibration file is missing"):
        read_stereo_calib(tmp_path, SIZE)
    (tmp_path / "calib.txt").write_text("P0: 300 0 160 0 0 300 120 0 0 0 1 0\n"
                                        "P1: 300 0 160 -90 0 300 120 0 0 0 1 0\n")
    assert read_stereo_calib(tmp_path, SIZE).baseline == pytest.approx(0.3)
    (tmp_path / "calib.yaml").write_text("x: 1\n")
    with pytest.raises(DatasetError, match="both calib.yaml and calib.txt"):
        read_stereo_calib(tmp_path, SIZE)


def _images(folder: Path, names: list[str], size=(160, 120), texture: bool = False) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for name in names:
        img = (rng.integers(0, 255, (size[1], size[0])) if texture
               else np.full((size[1], size[0]), 128)).astype(np.uint8)
        cv2.imwrite(str(folder / name), img)


def test_pairs_by_name_in_natural_order(tmp_path):
    names = ["f2.png", "f10.png", "f1.png"]
    _images(tmp_path / "left", names)
    _images(tmp_path / "right", names)
    (tmp_path / "left" / "notes.txt").write_text("not an image")
    pairs = find_pairs(tmp_path)
    assert [a.name for a, _ in pairs] == ["f1.png", "f2.png", "f10.png"]
    assert all(a.name == b.name and b.parent.name == "right" for a, b in pairs)
    (tmp_path / "right" / "f10.png").unlink()
    with pytest.raises(ImageError, match=r"right/f10.png: missing, the partner of .*left/f10.png"):
        find_pairs(tmp_path)
    _images(tmp_path / "right", ["f10.png", "f11.png"])
    with pytest.raises(ImageError, match=r"left/f11.png: missing, the partner of .*right/f11"):
        find_pairs(tmp_path)


def test_layout_errors_name_what_is_expected(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"no 'left' and 'right' image folders"):
        find_pairs(tmp_path)
    (tmp_path / "sequences").mkdir()
    with pytest.raises(FileNotFoundError, match="--source kitti"):
        find_pairs(tmp_path)
    _images(tmp_path / "image_0", ["000000.png"])
    with pytest.raises(FileNotFoundError, match=r"image_1: no such folder"):
        find_pairs(tmp_path)


def test_poses_at_reads_rows_and_interpolates():
    times = np.array([0.0, 0.1, 0.2, 1.5, 1.6])
    poses = np.array([[0, 0, 3.0], [1, 2, -3.0], [2, 2, 0.5], [5, 5, 0.0], [6, 5, 0.2]])
    at = np.array([-0.1, 0.1 + 1e-9, 0.05, 0.15, 1.0, 1.55, 1.6, 1.7])
    got = poses_at(times, poses, at, max_gap=1.0)
    assert np.isnan(got[0]).all() and np.isnan(got[4]).all() and np.isnan(got[7]).all()
    assert np.array_equal(got[1], poses[1]) and np.array_equal(got[6], poses[4])
    # halfway from yaw 3.0 to -3.0 is the shorter turn through pi, not 0
    turn = 2 * np.pi - 6.0
    assert got[2] == pytest.approx([0.5, 1.0, np.angle(np.exp(1j * (3.0 + turn / 2)))])
    # from -3.0 to 0.5 the shorter turn is 3.5 - 2 pi (clockwise)
    assert got[3] == pytest.approx([1.5, 2.0, -3.0 + 0.5 * (3.5 - 2 * np.pi) + 2 * np.pi])
    assert got[5] == pytest.approx([5.5, 5.0, 0.1])


def test_tum_errors_name_file_and_line(tmp_path):
    path = tmp_path / "groundtruth.txt"
    path.write_text("# t x y z qx qy qz qw\n0 0 0 0 0 0 0 1\n0.1 1 0 0 0 0 0 0\n")
    with pytest.raises(DatasetError, match=r"groundtruth.txt:3: quaternion of zero length"):
        read_tum_poses(path)
    path.write_text("0 0 0 0 0 0 0 1\n0 1 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"groundtruth.txt:2: time 0.0 is not after"):
        read_tum_poses(path)
    path.write_text("0 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"groundtruth.txt:1: expected 8 numbers, got 7"):
        read_tum_poses(path)


def _folder(tmp_path: Path, n: int = 4, texture: bool = False) -> Path:
    names = [f"{k:04d}.png" for k in range(n)]
    _images(tmp_path / "left", names, texture=texture)
    _images(tmp_path / "right", names, texture=texture)
    (tmp_path / "calib.txt").write_text("P0: 150 0 80 0 0 150 60 0 0 0 1 0\n"
                                        "P1: 150 0 80 -30 0 150 60 0 0 0 1 0\n")
    return tmp_path


def _tum(path: Path, times: np.ndarray, poses: np.ndarray) -> None:
    q = Rotation.from_euler("z", poses[:, 2:3]).as_quat()  # x y z w
    rows = np.column_stack([times, poses[:, :2], np.full(len(poses), 0.3), q])
    np.savetxt(path, rows, fmt="%.9f")


def test_wheel_odometry_is_the_fallback_and_times_keep_their_clock(tmp_path):
    """Blank images: VO fails on every frame, so each control is the odometry's increment
    between the frames (computed here by hand), on the clock of times.txt."""
    root = _folder(tmp_path)
    t0 = 1_700_000_000.0
    times = t0 + np.array([0.0, 0.1, 0.2, 0.3])
    np.savetxt(root / "times.txt", times, fmt="%.6f")
    odo_t = t0 + np.arange(0.0, 0.5, 0.05)
    odo = np.column_stack([0.5 * (odo_t - t0), 0.1 * (odo_t - t0) ** 2, 0.4 * (odo_t - t0)])
    _tum(root / "odometry.txt", odo_t, odo)
    _tum(root / "groundtruth.txt", odo_t, odo + [1.0, 2.0, 0.0])
    res = stereo_frontend(root, StereoParams(mount=mount_matrix(0.5, 10.0)))
    run = res.run
    assert res.summary.sources["wheel"] == 3
    assert run.timestamps == pytest.approx([0.0, 0.1, 0.2, 0.3], abs=1e-6)
    assert run.time_origin_ns == 1_700_000_000_000_000_000
    assert run.sensor == "stereo"  # the front-end marks its local maps (automatic ess_target)
    at = odo[::2][:4]  # the frames' rows
    for t in range(1, 4):
        dx, dy = at[t, :2] - at[t - 1, :2]
        c, s = np.cos(at[t - 1, 2]), np.sin(at[t - 1, 2])
        assert run.controls[t] == pytest.approx([c * dx + s * dy, -s * dx + c * dy,
                                                 at[t, 2] - at[t - 1, 2]], abs=1e-6)
    assert run.ground_truth == pytest.approx(at + [1.0, 2.0, 0.0], abs=1e-6)
    assert run.initial_pose == pytest.approx(at[0] + [1.0, 2.0, 0.0], abs=1e-6)


def test_times_and_ground_truth_errors(tmp_path):
    root = _folder(tmp_path)
    params = StereoParams(mount=mount_matrix(0.5))
    (root / "times.txt").write_text("0\n0.1\n0.2\n")
    with pytest.raises(DatasetError, match=r"times.txt: 3 times for 4 image pairs"):
        stereo_frontend(root, params)
    (root / "times.txt").write_text("0\n0.1\n0.1\n0.3\n")
    with pytest.raises(DatasetError, match=r"times.txt:3: time 0.1 of pair 2 is not after"):
        stereo_frontend(root, params)
    (root / "times.txt").unlink()
    (root / "groundtruth.txt").write_text("100 0 0 0 0 0 0 1\n101 1 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"groundtruth.txt: its times \(100.0 to 101.0 s\) "
                                           r"cover none of the frames .*0.1 s apart"):
        stereo_frontend(root, params)


def test_the_source_needs_the_mount_from_rig(tmp_path):
    root = _folder(tmp_path)
    spec = get_source("stereo")
    with pytest.raises(ConfigError, match=r"--source stereo .*: .*\[rig\] height"):
        spec.load(Source(source="stereo", path=root), Config(), None)
    seen = {}

    def fake(load, n, rig, t_robot_cam, times, params, **kw):
        seen.update(mount=t_robot_cam, n=n, stereo=params.stereo)
        raise RuntimeError("stop")

    import gslam_jax.datasets.stereo as stereo
    config = apply_overrides(Config(), ["rig.height=0.8", "rig.pitch=20",
                                        "stereo.num_disparities=32"])
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(stereo, "run_frontend", fake)
        with pytest.raises(RuntimeError, match="stop"):
            spec.load(Source(source="stereo", path=root, max_frames=2), config, None)
    assert np.allclose(seen["mount"], mount_matrix(0.8, 20.0)) and seen["n"] == 2
    assert seen["stereo"].num_disparities == 32


def test_raw_images_add_the_rectifying_rotation_to_the_mount(tmp_path, monkeypatch):
    left, right = _rectification()
    names = ["0.png", "1.png"]
    _images(tmp_path / "left", names, SIZE)
    _images(tmp_path / "right", names, SIZE)
    (tmp_path / "calib.yaml").write_text(_ros_yaml([left, right]))
    seen = {}
    import gslam_jax.datasets.stereo as stereo
    monkeypatch.setattr(stereo, "run_frontend", lambda *a, **k: seen.setdefault("m", a[3]))
    mount = mount_matrix(0.6, 15.0)
    stereo_frontend(tmp_path, StereoParams(mount=mount))
    # a point in the rectified left camera, X_raw = R^T X_rect, lands where the raw mount puts it
    x_rect = np.array([0.3, -0.2, 4.0])
    assert seen["m"][:3, :3] @ x_rect + seen["m"][:3, 3] == pytest.approx(
        mount[:3, :3] @ (left[2].T @ x_rect) + mount[:3, 3])


def test_image_size_must_match_the_calibration(tmp_path):
    root = _folder(tmp_path, n=2)
    (root / "calib.txt").unlink()
    left, right = _rectification()  # written for 320x240, the images are 160x120
    (root / "calib.yaml").write_text(_ros_yaml([left, right]))
    with pytest.raises(CalibrationError, match=r"image size 320x240 differs from the images' "
                                               r"160x120"):
        stereo_frontend(root, StereoParams(mount=mount_matrix(0.5)))


def test_open_yaml_names_a_missing_file(tmp_path):
    with pytest.raises(CalibrationError, match=r"nope.yaml: calibration file is missing"):
        open_yaml(tmp_path / "nope.yaml")


@pytest.mark.skipif(not KITTI.is_dir(), reason=f"real KITTI frames not found at {KITTI}")
def test_the_kitti_clip_as_a_stereo_folder_gives_the_kitti_run(tmp_path):
    """image_0/image_1 and calib.txt of the clip, its ground truth written as TUM in the robot
    frame by hand (level camera 1.65 m up, world = the robot at frame 0), [rig] height 1.65:
    the Run of --source kitti."""
    seq, n = KITTI / "sequences" / "seq1", 4
    for d in ("image_0", "image_1"):
        (tmp_path / d).mkdir()
        for k in range(n):
            (tmp_path / d / f"{k:06d}.png").symlink_to((seq / d / f"{k:06d}.png").resolve())
    shutil.copy(seq / "calib.txt", tmp_path / "calib.txt")
    cams = read_kitti_poses(KITTI / "poses" / "seq1.txt")
    # camera (x right, y down, z forward) -> robot (x forward, y left, z up), 1.65 m up
    t_rc = np.eye(4)
    t_rc[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]
    t_rc[2, 3] = 1.65
    robot = [t_rc @ np.linalg.inv(cams[0]) @ c @ np.linalg.inv(t_rc) for c in cams]
    gt = np.array([[p[0, 3], p[1, 3], np.arctan2(p[1, 0], p[0, 0])] for p in robot])
    _tum(tmp_path / "groundtruth.txt", 0.1 * np.arange(len(gt)), gt)
    config = apply_overrides(Config(), ["stereo.num_disparities=128"])
    a = get_source("kitti").load(Source(source="kitti", path=KITTI, max_frames=n), config,
                                 None).run
    b = get_source("stereo").load(Source(source="stereo", path=tmp_path),
                                  apply_overrides(config, ["rig.height=1.65"]), None).run
    assert b.num_frames == n and np.array_equal(a.obs_index, b.obs_index)
    for name in ("controls", "timestamps", "ground_truth", "initial_pose"):
        assert np.allclose(getattr(a, name), getattr(b, name), atol=1e-6), name
    assert np.allclose(a.local_maps, b.local_maps, atol=1e-6)
    assert a.resolution == b.resolution and b.time_origin_ns is None
    assert isinstance(read_stereo_calib(tmp_path, (1226, 370)), RectifiedRig)


def test_disparity_range_from_the_calibration():
    """Multiples of 16 that reach disparity fx * baseline / 3 m, never fewer than 64."""
    from gslam_jax.vo.stereo import disparities_from_depth

    assert disparities_from_depth(707.0912, 379.8145 / 707.0912) == 128  # KITTI: 126.6 px
    assert disparities_from_depth(718.856, 0.5372) == 144  # KITTI 00-02: 128.7 px
    assert disparities_from_depth(458.0, 0.11) == 64  # EuRoC: 16.8 px, the floor
    assert disparities_from_depth(960.0, 0.3) == 96  # exactly 96 px


@pytest.mark.skipif(not KITTI.is_dir(), reason=f"real KITTI frames not found at {KITTI}")
def test_the_kitti_clip_through_a_ros_yaml_folder_gives_kittis_vo(tmp_path):
    """The clip's images as left/ right/ with a per-camera ROS calib.yaml (K and P from calib.txt,
    D = 0, R = I) and no [stereo] settings: the same VO path as --source kitti (both readers
    take the dense search range from the calibration, 128 disparities here)."""
    seq, n = KITTI / "sequences" / "seq1", 5
    for src, dst in (("image_0", "left"), ("image_1", "right")):
        (tmp_path / dst).mkdir()
        for k in range(n):
            (tmp_path / dst / f"{k:06d}.png").symlink_to((seq / src / f"{k:06d}.png").resolve())
    proj = {}
    for line in (seq / "calib.txt").read_text().splitlines():
        key, _, rest = line.partition(":")
        proj[key.strip()] = np.array(rest.split(), float).reshape(3, 4)
    cams = [(p[:, :3], np.zeros(5), np.eye(3), p) for p in (proj["P0"], proj["P1"])]
    (tmp_path / "calib.yaml").write_text(_ros_yaml(cams, size=(1226, 370)))
    a = get_source("kitti").load(Source(source="kitti", path=KITTI, max_frames=n), Config(),
                                 None).run
    b = get_source("stereo").load(Source(source="stereo", path=tmp_path),
                                  apply_overrides(Config(), ["rig.height=1.65"]), None).run
    np.testing.assert_allclose(b.controls, a.controls, atol=1e-6)
    np.testing.assert_allclose(b.vo_poses(), a.vo_poses(), atol=1e-6)
