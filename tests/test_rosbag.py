"""The rosbag source: bags written with rosbags' writers (ROS 1, ROS 2 sqlite3 and MCAP) from the
real KITTI and EuRoC frames give the Run of the folder sources; compressed images, unmatched
frames, the wheel/IMU fallback, topic picking and its errors."""

from __future__ import annotations

import contextlib
import io
import shlex
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

pytest.importorskip("rosbags", reason="the rosbag extra (pip install 'gslam-jax[rosbag]')")

from bagwriter import BagWriter  # noqa: E402

from gslam_jax.app.cli import main  # noqa: E402
from gslam_jax.config import Config, ConfigError, apply_overrides  # noqa: E402
from gslam_jax.datasets.euroc import EurocParams, euroc_frontend, read_sensor_yaml  # noqa: E402
from gslam_jax.datasets.kitti import KittiParams, kitti_frontend, read_kitti_poses  # noqa: E402
from gslam_jax.datasets.mount import camera_mount  # noqa: E402
from gslam_jax.datasets.reading import quat_to_matrix  # noqa: E402
from gslam_jax.datasets.rosbag import (MissingExtraError, RosbagParams,  # noqa: E402
                                       rosbag_frontend)
from gslam_jax.datasets.rosbag_msgs import TfTree  # noqa: E402
from gslam_jax.datasets.rosbag_topics import TopicInfo, pair_stamps, pick_topics  # noqa: E402
from gslam_jax.errors import DatasetError  # noqa: E402
from gslam_jax.vo.calib import CalibrationError, CameraModel  # noqa: E402
from gslam_jax.vo.frontend import FrontEndParams  # noqa: E402
from gslam_jax.vo.geometry import increments_2d, invert, make_transform  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
KITTI, EUROC = DATA / "kitti-stereo-51", DATA / "euroc-v1_01-static-20"
T0 = 1_700_000_000 * 10**9  # the bags' first stamp (ns)
N_KITTI, N_EUROC = 3, 4
RUN_FIELDS = ("controls", "obs_index", "local_maps", "timestamps", "ground_truth", "vo_failed",
              "initial_pose")
# rosbags' writers leave their own warnings aside; the source's are checked where they matter
pytestmark = pytest.mark.filterwarnings("ignore:.*camera mount is not in the bag")


def _same_run(a, b, atol: float = 1e-6) -> None:
    for name in RUN_FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            np.testing.assert_allclose(np.asarray(x, float), np.asarray(y, float), atol=atol,
                                       err_msg=name)


def _bag_path(tmp: Path, name: str, fmt: str) -> Path:
    return tmp / (f"{name}.bag" if fmt == "ros1" else f"{name}_{fmt}")


@pytest.fixture(scope="module")
def kitti() -> dict:
    """The first frames of the KITTI clip, its cameras (rectified: D = 0, R = I, P from
    P0/P1) and camera poses (``poses/seq1.txt``)."""
    seq = KITTI / "sequences" / "seq1"
    if not seq.is_dir():
        pytest.skip(f"real KITTI frames not found at {KITTI} (see shared/data/README.md)")
    cv2.setNumThreads(1)
    p = {}
    for line in (seq / "calib.txt").read_text().splitlines():
        key, _, rest = line.partition(":")
        p[key.strip()] = np.array(rest.split(), float).reshape(3, 4)
    imgs = [[cv2.imread(str(seq / cam / f"{t:06d}.png"), cv2.IMREAD_GRAYSCALE)
             for cam in ("image_0", "image_1")] for t in range(N_KITTI + 1)]
    size = (imgs[0][0].shape[1], imgs[0][0].shape[0])
    cams = [CameraModel(p[k][:, :3], np.zeros(5), np.eye(3), p[k], size) for k in ("P0", "P1")]
    cam = read_kitti_poses(KITTI / "poses" / "seq1.txt")
    folder = kitti_frontend(KITTI, KittiParams(max_frames=N_KITTI)).run
    return {"images": imgs, "cams": cams, "camera": cam[:N_KITTI + 1], "folder": folder}


# x forward, y left, z up from KITTI's camera axes (x right, y down, z forward), level, 1.65 m
LEVEL = make_transform(np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]]), [0.0, 0.0, 1.65])


def _write_kitti(path: Path, fmt: str, kitti: dict, encodings=("mono8", "mono8"),
                 n: int = N_KITTI, mount: np.ndarray = LEVEL) -> None:
    """The KITTI frames as a bag; the ground truth is the robot's pose (world: the robot at
    frame 0, z up) with the camera at ``mount``."""
    cam = kitti["camera"]
    robot = [mount @ invert(cam[0]) @ c @ invert(mount) for c in cam]
    with BagWriter(path, fmt) as w:
        for t in range(n):
            ns = T0 + t * 100_000_000
            for side, cam, frame, enc in zip(("left", "right"), kitti["cams"], ("cam0", "cam1"),
                                             encodings):
                w.camera_info(f"/kitti/{side}/camera_info", ns, cam, frame)
                w.image(f"/kitti/{side}/image_raw", ns, kitti["images"][t][side == "right"],
                        frame, enc)
            w.pose("/ground_truth/pose", ns, robot[t])


@pytest.mark.parametrize("fmt,encodings", [("ros1", ("rgb8", "bgr8")),
                                           ("sqlite3", ("mono8", "mono8")),
                                           ("mcap", ("mono16", "mono8"))])
def test_kitti_bag_gives_the_folder_run(kitti, tmp_path, fmt, encodings):
    bag = _bag_path(tmp_path, "kitti", fmt)
    _write_kitti(bag, fmt, kitti, encodings)
    with pytest.warns(UserWarning, match="camera mount is not in the bag"):
        out = rosbag_frontend(bag, RosbagParams(frontend=KittiParams().frontend))
    assert out.topics["left"] == "/kitti/left/image_raw"
    assert out.topics["ground_truth"] == "/ground_truth/pose"
    assert out.topics["wheel"] is None and out.topics["imu"] is None
    assert len(out.pairing.left) == N_KITTI and not len(out.pairing.unmatched_right)
    assert out.rig.maps is None  # D = 0, R = I: no remap
    np.testing.assert_allclose(out.rig.baseline, 379.8145 / 707.0912, rtol=1e-6)
    run = out.result.run
    assert run.time_origin_ns == T0
    _same_run(kitti["folder"], run)
    assert np.abs(run.controls[1:, 0]).max() > 0.5  # the car moves: a check that can fail


@pytest.fixture(scope="module")
def euroc(tmp_path_factory) -> dict:
    """An MCAP bag of the first EuRoC frames: raw images, CameraInfo with K, D and R, P from
    cv2.stereoRectify, the IMU in its own frame, the ground truth of the body (Odometry with
    child frame imu0) and /tf_static placing the body and the cameras on the robot, whose frame
    is the EuRoC adapter's (z up along the still accelerometer, x along cam0's axis, origin on
    the ground below the body)."""
    mav = EUROC / "mav0"
    if not mav.is_dir():
        pytest.skip(f"real EuRoC frames not found at {EUROC} (see shared/data/README.md)")
    cv2.setNumThreads(1)
    c0, c1 = (read_sensor_yaml(mav / c / "sensor.yaml") for c in ("cam0", "cam1"))
    t10 = invert(c1.t_bs) @ c0.t_bs
    r0, r1, p0, p1, *_ = cv2.stereoRectify(c0.k, c0.dist, c1.k, c1.dist, c0.size, t10[:3, :3],
                                           t10[:3, 3].reshape(3, 1),
                                           flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.0)
    cams = [CameraModel(c0.k, c0.dist, r0, p0, c0.size), CameraModel(c1.k, c1.dist, r1, p1,
                                                                     c1.size)]

    def table(name: str) -> tuple[np.ndarray, np.ndarray]:
        path = mav / name / "data.csv"
        return (np.loadtxt(path, delimiter=",", dtype=np.int64, usecols=0),
                np.loadtxt(path, delimiter=","))

    frames = np.loadtxt(mav / "cam0" / "data.csv", delimiter=",", dtype=np.int64, usecols=0)
    imu_t, imu = table("imu0")
    gt_t, gt = table("state_groundtruth_estimate0")
    win = (imu_t >= frames[0]) & (imu_t <= frames[0] + 100_000_000)
    acc = imu[win, 4:7]
    up = acc[np.abs(np.linalg.norm(acc, axis=1) - 9.81) < 0.3].mean(axis=0)
    up /= np.linalg.norm(up)
    fwd = c0.t_bs[:3, 2] - up * (c0.t_bs[:3, 2] @ up)
    fwd /= np.linalg.norm(fwd)
    t_body_robot = make_transform(np.column_stack([fwd, np.cross(up, fwd), up]),
                                  -gt[0, 3] * up)
    bag = tmp_path_factory.mktemp("euroc") / "euroc_mcap"
    with BagWriter(bag, "mcap") as w:
        w.tf_static(int(frames[0]), [("base_footprint", "imu0", invert(t_body_robot)),
                                     ("imu0", "cam0", c0.t_bs), ("imu0", "cam1", c1.t_bs)])
        for t in range(N_EUROC):
            ns = int(frames[t])
            for cam, c in (("cam0", cams[0]), ("cam1", cams[1])):
                w.camera_info(f"/{cam}/camera_info", ns, c, cam)
                w.image(f"/{cam}/image_raw", ns, cv2.imread(str(mav / cam / "data" / f"{ns}.png"),
                                                            cv2.IMREAD_GRAYSCALE), cam)
        for row, ns in zip(gt, gt_t):
            w.odometry("/vicon/ground_truth", int(ns),
                       make_transform(quat_to_matrix(row[4:8]), row[1:4]), "world", "imu0")
        for row, ns in zip(imu, imu_t):
            w.imu("/imu0", int(ns), row[1:4], row[4:7], "imu0")
    return {"bag": bag, "root": EUROC}


def test_euroc_bag_gives_the_folder_run(euroc):
    out = rosbag_frontend(euroc["bag"])
    assert out.topics["imu"] == "/imu0" and out.topics["ground_truth"] == "/vicon/ground_truth"
    assert out.mount_from == "/tf_static base_footprint -> cam0"
    assert out.rig.maps is not None  # raw images: rectified with K, D, R, P
    folder = euroc_frontend(euroc["root"], EurocParams(max_frames=N_EUROC))
    _same_run(folder.run, out.result.run)
    assert out.result.run.time_origin_ns == folder.run.time_origin_ns
    assert out.result.summary.tilt_corrections == folder.summary.tilt_corrections > 0


def _readme_bag_example() -> list[str]:
    """The README's worked bag example, as arguments after ``gslam``."""
    readme = Path(__file__).resolve().parents[1] / "README.md"
    lines = [ln for ln in readme.read_text().splitlines()
             if ln.startswith("gslam run --source rosbag --path drive.bag --set")]
    assert len(lines) == 1, "the README's worked bag example"
    return shlex.split(lines[0])[1:]


def test_readme_bag_example_gives_the_folder_trajectory(kitti, tmp_path):
    """The README's example run on a bag of the KITTI frames, and the KITTI folder with the
    same [rig] settings: the same trajectory."""
    example = _readme_bag_example()
    rig = [a for i, v in enumerate(example[1:]) if example[i] == "--set"
           and v.startswith("rig.") for a in ("--set", v)]
    assert rig, "the example sets the mount with [rig]"
    # the truth as a robot with that mount sees it (as the KITTI source makes it)
    mount = camera_mount(apply_overrides(Config(), rig[1::2]), LEVEL, "test")
    bag = tmp_path / "drive_mcap"
    _write_kitti(bag, "mcap", kitti, mount=mount)
    where = {"drive.bag": str(bag), "results/drive": str(tmp_path / "bag")}
    runs = {"bag": [where.get(a, a) for a in example],
            "folder": ["run", "--source", "kitti", "--path", str(KITTI), "--max-frames",
                       str(N_KITTI), *rig, "--out", str(tmp_path / "folder")]}
    for name, args in runs.items():
        with contextlib.redirect_stdout(io.StringIO()) as printed:
            assert main([*args, "--set", "filter.particles=4",
                         "--set", "stereo.num_disparities=128"]) == 0
        if name == "bag":
            text = printed.getvalue()
            assert "stereo pairs: 3, unmatched: 0 left, 0 right; camera mount: [rig]" in text
    for name in ("trajectory_tum.txt", "ground_truth_tum.txt"):
        a, b = (np.loadtxt(tmp_path / k / name) for k in ("folder", "bag"))
        assert len(a) == len(b) == N_KITTI
        np.testing.assert_allclose(b[:, 0] - b[0, 0], a[:, 0] - a[0, 0], atol=1e-6)  # seconds
        np.testing.assert_allclose(b[:, 1:], a[:, 1:], atol=1e-6)  # x y z qx qy qz qw
        assert b[0, 0] == pytest.approx(T0 * 1e-9)  # the bag's clock
        assert np.linalg.norm(a[-1, 1:3] - a[0, 1:3]) > 1.0  # the car moved: a check that fails


def test_compressed_images_unmatched_frame_and_wheel_imu_fallback(kitti, tmp_path):
    """PNG CompressedImage pairs, one right image without a left partner (counted), a corrupt
    left image bridged by the wheel odometry and the IMU (on_bad_frame fallback)."""
    bag = tmp_path / "fallback_sqlite3"
    n = 4
    v, vy, w_yaw = 6.0, 0.2, 0.1  # odometry: x = v t, y = vy t, yaw = w_yaw t (s from T0)

    def odom(t: float) -> np.ndarray:
        c, s = np.cos(w_yaw * t), np.sin(w_yaw * t)
        return make_transform(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]),
                              [v * t, vy * t, 0.0])

    with BagWriter(bag, "sqlite3") as w:
        for t in range(n):
            ns = T0 + t * 100_000_000
            for side, cam, frame in zip(("left", "right"), kitti["cams"], ("cam0", "cam1")):
                w.camera_info(f"/stereo/{side}/camera_info", ns, cam, frame)
                img = kitti["images"][t][side == "right"]
                bad = side == "left" and t == 2
                w.compressed(f"/stereo/{side}/image_raw/compressed", ns,
                             b"not an image" if bad else img, frame)
        w.compressed("/stereo/right/image_raw/compressed", T0 + 250_000_000,
                     kitti["images"][3][1], "cam1")  # no left image within 10 ms
        for k in range(-2, 2 * n + 2):  # 20 Hz, half a frame off the cameras' stamps
            ns = T0 + k * 50_000_000 + 25_000_000
            w.odometry("/wheel/odom", ns, odom((ns - T0) * 1e-9))
        for k in range(0, 10 * n):  # 100 Hz: still for the first 0.1 s, then turning
            ns = T0 + k * 10_000_000
            w.imu("/imu", ns, np.array([0.0, 0.0, 0.0 if k <= 10 else 0.3]),
                  np.array([0.0, 0.0, 9.81]), "base_footprint")
    params = RosbagParams(frontend=FrontEndParams(dense=False, on_bad_frame="fallback"))
    with pytest.warns(UserWarning, match=r"0 left image\(s\) .* and 1 right image\(s\)"):
        out = rosbag_frontend(bag, params)
    assert out.topics["wheel"] == "/wheel/odom" and out.topics["imu"] == "/imu"
    assert out.pairing.unmatched_right.tolist() == [T0 + 250_000_000]
    assert len(out.pairing.left) == n and not len(out.pairing.unmatched_left)
    summary, run = out.result.summary, out.result.run
    assert [t for t, _ in summary.bad_frames] == [2]
    assert "compressed image" in summary.bad_frames[0][1]
    # frame 2 (bad) and frame 3 (VO has no previous frame) come from wheels + gyro
    assert summary.sources["wheel+imu"] == 2 and run.vo_failed.tolist() == [0, 0, 1, 1]
    truth = increments_2d(np.array([[v * s, vy * s, w_yaw * s] for s in 0.1 * np.arange(n)]))
    np.testing.assert_allclose(run.controls[2:, :2], truth[2:, :2], atol=1e-9)
    np.testing.assert_allclose(run.controls[2:, 2], 0.3 * 0.1, atol=1e-6)  # the gyro's yaw


def _tiny_bag(path: Path, topics: dict[str, str], n: int = 3, fmt: str = "sqlite3",
              zero_stamps: bool = False, k_scale: float = 1.0) -> None:
    """A bag of small random stereo images on the image topics of ``topics`` (name -> kind:
    "image", "info_left", "info_right", "odom")."""
    rng = np.random.default_rng(0)
    size = (64, 48)
    p = np.array([[50.0, 0, 32, 0], [0, 50, 24, 0], [0, 0, 1, 0]])
    cams = {"info_left": CameraModel(p[:, :3] * k_scale, np.zeros(5), np.eye(3), p * k_scale,
                                     size)}
    p1 = p.copy()
    p1[0, 3] = -50.0 * 0.1
    cams["info_right"] = CameraModel(p[:, :3] * k_scale, np.zeros(5), np.eye(3), p1 * k_scale,
                                     size)
    with BagWriter(path, fmt) as w:
        for t in range(n):
            ns = T0 + t * 50_000_000
            for name, kind in topics.items():
                if kind == "image":
                    img = rng.integers(0, 255, (size[1], size[0])).astype(np.uint8)
                    w.image(name, 0 if zero_stamps else ns, img, bag_ns=ns)
                elif kind.startswith("info"):
                    w.camera_info(name, ns, cams[kind])
                else:
                    w.odometry(name, ns, np.eye(4))


STEREO = {"/stereo/left/image_raw": "image", "/stereo/right/image_raw": "image",
          "/stereo/left/camera_info": "info_left", "/stereo/right/camera_info": "info_right"}
FAST = RosbagParams(frontend=FrontEndParams(dense=False))


def test_topics_are_picked_or_listed_in_the_error(tmp_path):
    bag = tmp_path / "two_left"
    _tiny_bag(bag, {**STEREO, "/stereo/left/image_rect": "image"})
    with pytest.raises(DatasetError, match="2 candidate.*left topic.*/stereo/left/image_raw "
                       r"\(sensor_msgs/Image, 3\), /stereo/left/image_rect .*--topic left=NAME"):
        rosbag_frontend(bag, FAST)
    out = rosbag_frontend(bag, RosbagParams(topics={"left": "/stereo/left/image_rect"},
                                            max_frames=2, frontend=FAST.frontend))
    assert out.topics["left_info"] == "/stereo/left/camera_info"
    assert out.result.run.num_frames == 2 and not len(out.pairing.unmatched_right)
    # the storage file itself, not its folder
    one = rosbag_frontend(bag / "two_left.db3", RosbagParams(
        topics={"left": "/stereo/left/image_rect"}, max_frames=2, frontend=FAST.frontend))
    _same_run(out.result.run, one.result.run, atol=0.0)
    with pytest.raises(DatasetError, match="--topic right=/nope: no such topic.*"
                       "/stereo/right/image_raw"):
        rosbag_frontend(bag, RosbagParams(topics={"right": "/nope"}))
    with pytest.raises(ConfigError, match="unknown role 'depth'; roles: left, right"):
        rosbag_frontend(bag, RosbagParams(topics={"depth": "/x"}))


def test_pick_topics_rules():
    info = TopicInfo
    image, cinfo, odom = "sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo", \
        "nav_msgs/msg/Odometry"
    topics = {"/cam0/image_raw": info(image, 5), "/cam1/image_raw": info(image, 5),
              "/cam0/camera_info": info(cinfo, 5), "/cam1/camera_info": info(cinfo, 5),
              "/odom": info(odom, 9), "/odometry/filtered": info(odom, 9),
              "/vicon/pose": info("geometry_msgs/msg/PoseStamped", 9)}
    with pytest.raises(DatasetError, match=r"2 candidate\(s\) for the wheel topic; candidates: "
                       r"/odom .*/odometry/filtered .*--topic wheel=NAME, or --topic wheel= "
                       "for none"):
        pick_topics(topics, {}, "b")
    got = pick_topics(topics, {"wheel": None}, "b")
    assert got == {"left": "/cam0/image_raw", "right": "/cam1/image_raw",
                   "left_info": "/cam0/camera_info", "right_info": "/cam1/camera_info",
                   "wheel": None, "imu": None, "ground_truth": "/vicon/pose"}
    no_hint = {"/a/image": info(image, 1), "/b/image": info(image, 1)}
    with pytest.raises(DatasetError, match="no candidate.*left topic; sensor_msgs/msg/Image or "
                       r"sensor_msgs/msg/CompressedImage topics: /a/image \(sensor_msgs/Image"):
        pick_topics(no_hint, {}, "b")
    with pytest.raises(DatasetError, match="carries sensor_msgs/msg/Image, not"):
        pick_topics(topics, {"imu": "/cam0/image_raw"}, "b")


def test_pairs_are_one_to_one_within_the_tolerance():
    rng = np.random.default_rng(1)
    base = np.arange(200) * 50_000_000
    left = base + rng.integers(-2_000_000, 2_000_000, 200)
    right = base + rng.integers(-2_000_000, 2_000_000, 200)
    drop_l, drop_r = [5, 77, 150], [20, 120]
    left, right = np.delete(left, drop_l), np.delete(right, drop_r)
    p = pair_stamps(left, right, 10_000_000)
    assert len(set(p.left.tolist())) == len(p.left) and len(set(p.right.tolist())) == len(p.right)
    assert np.abs(left[p.left] - right[p.right]).max() <= 10_000_000
    assert len(p.left) == 200 - 5  # every frame whose partner was not dropped
    # a frame whose partner was dropped is unmatched: its position among the frames kept
    kept_l, kept_r = np.delete(np.arange(200), drop_l), np.delete(np.arange(200), drop_r)
    assert p.unmatched_left.tolist() == left[np.searchsorted(kept_l, drop_r)].tolist()
    assert p.unmatched_right.tolist() == right[np.searchsorted(kept_r, drop_l)].tolist()
    assert len(p.left) + len(p.unmatched_left) == len(left)


def test_zero_header_stamps_use_the_record_time(tmp_path):
    bag = tmp_path / "zero.bag"
    _tiny_bag(bag, STEREO, fmt="ros1", zero_stamps=True)
    with pytest.warns(UserWarning, match="every header stamp is zero"):
        run = rosbag_frontend(bag, FAST).result.run
    np.testing.assert_allclose(run.timestamps, [0.0, 0.05, 0.1], atol=1e-12)
    assert run.time_origin_ns == T0


def test_uncalibrated_camera_is_named(tmp_path):
    bag = tmp_path / "uncalibrated"
    _tiny_bag(bag, STEREO, k_scale=0.0)
    with pytest.raises(CalibrationError, match="/stereo/left/camera_info: field 'K' is all "
                       "zero: the camera is not calibrated"):
        rosbag_frontend(bag, FAST)


def test_rect_topics_are_not_rectified_again(tmp_path):
    bag = tmp_path / "rect"
    _tiny_bag(bag, {"/left/image_rect": "image", "/right/image_rect": "image",
                    "/left/camera_info": "info_left", "/right/camera_info": "info_right"})
    assert rosbag_frontend(bag, FAST).rig.maps is None


def test_missing_library_names_the_extra(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)
    with pytest.raises(MissingExtraError, match=r"pip install 'gslam-jax\[rosbag\]'"):
        rosbag_frontend(tmp_path / "x.bag")


def test_not_a_bag_and_topic_option_checks(tmp_path, capsys):
    folder = tmp_path / "empty"
    folder.mkdir()
    with pytest.raises(DatasetError, match="not a readable bag .*metadata.yaml"):
        rosbag_frontend(folder)
    assert main(["run", "--source", "kitti", "--path", str(KITTI), "--topic", "left=/x"]) == 2
    assert "--topic is for --source rosbag, not --source kitti" in capsys.readouterr().err


def test_static_transforms_compose_along_the_tree(tmp_path):
    rng = np.random.default_rng(2)

    def random_pose() -> np.ndarray:
        return make_transform(quat_to_matrix(rng.normal(size=4)), rng.normal(size=3))

    a_b, b_c, b_d = random_pose(), random_pose(), random_pose()
    tree = TfTree()
    tree.add(BagWriter(tmp_path / "unused", "sqlite3").tf_message(
        0, [("a", "b", a_b), ("b", "c", b_c), ("/b", "d", b_d)]))  # ROS 1's leading '/'
    np.testing.assert_allclose(tree.lookup("c", "a"), invert(a_b @ b_c), atol=1e-9)
    np.testing.assert_allclose(tree.lookup("d", "c"), invert(b_d) @ b_c, atol=1e-9)
    np.testing.assert_allclose(tree.lookup("a", "a"), np.eye(4))
    assert tree.lookup("a", "zz") is None
