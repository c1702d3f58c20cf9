"""ROS bag adapter (``--source rosbag --path BAG``): ROS 1 ``.bag`` files and ROS 2 bags (the
bag's folder holding ``metadata.yaml``, sqlite3 or MCAP storage, or its ``.db3``/``.mcap`` file),
read with the pure-Python ``rosbags`` library (``pip install 'gslam-jax[rosbag]'``; no ROS).

Topics by role (``rosbag_topics``: picked when one topic fits, else ``--topic ROLE=NAME``): the
left and right images (``sensor_msgs/Image`` mono8, rgb8, bgr8, rgba8, bgra8, mono16, or
``CompressedImage``), each camera's ``CameraInfo`` (K, D, R, P: raw images are rectified with
them; a topic named ``..._rect...`` is taken as rectified already, ROS's ``image_proc``
convention, and only its P is used), and optionally wheel odometry (``nav_msgs/Odometry``),
an IMU (``sensor_msgs/Imu``) and a ground-truth pose topic.

Time: header stamps (a topic whose stamps are all zero uses the bag's record times, with a
warning). A left and a right image form a pair when each is the other's nearest and they are
at most ``pair_tolerance`` apart; every other image is counted and reported as unmatched (a
warning, and the printed summary). The Run's times are seconds from the first pair; its
``time_origin_ns`` is that pair's stamp.

Frames: the robot frame is REP 103's (x forward, y left, z up; origin on the ground). The camera
mount (raw left camera to robot) is, by default, the bag's static transform (``/tf_static``)
from ``base_footprint`` (or ``base_link``, whose origin is then taken as the ground) to the
left camera's ``frame_id``; without one, a level camera 1.65 m above the ground, with a warning.
The config's [rig] changes it (``datasets.mount.camera_mount``). The IMU's, odometry's and
ground truth's frames are carried into the robot frame through ``/tf_static`` where it links
them to the camera; otherwise their axes are taken as the robot's. Odometry and ground-truth
worlds are taken as z up (REP 103). Both are interpolated at the frame times (frames outside
their span, or between samples more than ``pose_gap`` apart, get NaN: no wheel increment, no
ground truth there). The IMU is used as in the EuRoC adapter: the mean specific force since the
previous frame (tilt correction), the gyro about "up" integrated between frames (fallback
heading), its bias removed when it is still in the first ``gravity_window`` seconds.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, NamedTuple

import numpy as np

from gslam_jax.config import Config, ConfigError
from gslam_jax.datasets.mount import camera_mount
from gslam_jax.datasets.registry import DataSource, LoadedSource, Source, stereo_settings
from gslam_jax.datasets.rosbag_msgs import (TF, TfTree, camera_model, decode_image,
                                            pose_matrix, stamp_ns)
from gslam_jax.datasets.rosbag_sensors import Series, imu_aids, planar_poses
from gslam_jax.datasets.rosbag_topics import (ROLES, Pairing, TopicInfo, check_roles,
                                              pair_stamps, pick_topics, rectified_topic)
from gslam_jax.errors import DatasetError, InputError
from gslam_jax.run import Run
from gslam_jax.vo.calib import CameraModel, RectifiedRig
from gslam_jax.vo.frontend import FrontEndParams, FrontEndResult, SensorAids, run_frontend
from gslam_jax.vo.geometry import CAM_TO_ROBOT_AXES, increments_2d, make_transform
from gslam_jax.vo.localmap import localmap_params
from gslam_jax.vo.stereo import DenseStereoParams

__all__ = ["RosbagParams", "RosbagFrontEnd", "MissingExtraError", "rosbag_frontend",
           "load_rosbag", "DEFAULT_MOUNT", "ROBOT_FRAMES"]

ROBOT_FRAMES = ("base_footprint", "base_link")  # tf frames taken as the robot's, in this order
DEFAULT_MOUNT = make_transform(CAM_TO_ROBOT_AXES, [0.0, 0.0, 1.65])  # level, 1.65 m (KITTI's)
NS = 1_000_000_000


class MissingExtraError(InputError):
    """The optional ``rosbags`` library is not installed."""


@dataclass(frozen=True)
class RosbagParams:
    """topics: role -> topic name (None or '': none; roles left out are picked). max_frames:
    at most this many pairs. pair_tolerance (s): the most a left and a right stamp of a pair
    differ. pose_gap (s): odometry and ground-truth samples further apart are not interpolated
    between. gravity_window, gyro_still, max_gyro_bias: the IMU's still start and gyro bias,
    as :class:`gslam_jax.datasets.euroc.EurocParams`. mount: None, or a function of the default
    mount (4x4 raw left camera to robot; see the module docstring) returning the one to use
    (``gslam run``: the config's [rig] through ``camera_mount``)."""

    topics: Mapping[str, str | None] = field(default_factory=dict)
    max_frames: int | None = None
    pair_tolerance: float = 0.01
    pose_gap: float = 1.0
    gravity_window: float = 0.1
    gyro_still: float = 0.02
    max_gyro_bias: float = 0.12
    frontend: FrontEndParams = field(default_factory=FrontEndParams)
    mount: Callable[[np.ndarray], np.ndarray] | None = None


class RosbagFrontEnd(NamedTuple):
    """What :func:`rosbag_frontend` returns: the front-end's result, the topic of each role
    (None: not used), the stereo pairing (unmatched frames), the rig the CameraInfo made and
    how the camera mount was found."""

    result: FrontEndResult
    topics: dict[str, str | None]
    pairing: Pairing
    rig: RectifiedRig
    mount_from: str

    def text(self) -> str:
        """Topics, pairs and unmatched frames, then the front-end's summary."""
        p = self.pairing
        used = ", ".join(f"{role} {name or 'none'}" for role, name in self.topics.items())
        return (f"topics: {used}\nstereo pairs: {len(p.left)}, unmatched: "
                f"{len(p.unmatched_left)} left, {len(p.unmatched_right)} right; camera mount: "
                f"{self.mount_from}\n{self.result.summary.text()}")


def _rosbags() -> tuple[Any, Any]:
    """(AnyReader, default typestore), or MissingExtraError naming the extra."""
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError as err:
        raise MissingExtraError("--source rosbag needs the rosbags library: pip install "
                                f"'gslam-jax[rosbag]' (or pip install rosbags); {err}") from None
    return AnyReader, get_typestore(Stores.ROS2_HUMBLE)


def _open(path: Path) -> Any:
    reader_cls, typestore = _rosbags()
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such bag (a ROS 1 .bag file, or a ROS 2 bag folder "
                                "or its .db3/.mcap file)")
    try:
        reader = reader_cls([path], default_typestore=typestore)
        reader.open()
    except Exception as err:  # noqa: BLE001 - rosbags' errors differ by format and version
        hint = (" (a ROS 2 bag folder holds metadata.yaml; a ROS 1 bag is a .bag file)"
                if path.is_dir() else "")
        raise DatasetError(f"{path}: not a readable bag{hint}: {err}") from None
    return reader


def _topics(reader: Any) -> dict[str, TopicInfo]:
    return {name: TopicInfo(info.msgtype, int(info.msgcount or 0))
            for name, info in reader.topics.items()}


def _read(reader: Any, picked: dict[str, str | None], bag: Path) -> tuple[dict[str, Series],
                                                                         TfTree]:
    """First pass: stamps of the image topics, every message of the others, /tf_static."""
    roles_of: dict[str, list[str]] = {}
    for role, name in picked.items():
        if name:
            roles_of.setdefault(name, []).append(role)
    tf_topics = {n for n, i in _topics(reader).items()
                 if i.msgtype == TF and n.rstrip("/").endswith("tf_static")}
    series = {role: Series() for role in ROLES}
    tree = TfTree()
    conns = [c for c in reader.connections if c.topic in roles_of or c.topic in tf_topics]
    try:
        for conn, bag_ns, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.topic in tf_topics:
                tree.add(msg)
            for role in roles_of.get(conn.topic, []):
                if role in ("left", "right"):
                    series[role].add(msg, bag_ns)
                elif role in ("left_info", "right_info"):
                    if series[role].first is None:
                        series[role].add(msg, bag_ns)
                elif role == "imu":
                    a, w = msg.linear_acceleration, msg.angular_velocity
                    series[role].add(msg, bag_ns, (w.x, w.y, w.z, a.x, a.y, a.z))
                else:
                    series[role].add(msg, bag_ns, pose_matrix(msg, conn.msgtype))
    except InputError:
        raise
    except Exception as err:  # noqa: BLE001 - a corrupt bag fails inside rosbags
        raise DatasetError(f"{bag}: reading the bag failed: {err}") from None
    return series, tree


def _sorted_stamps(s: Series, where: str) -> np.ndarray:
    """The image stamps, sorted; DatasetError for none, or for a stamp given twice."""
    if not s.stamps:
        raise DatasetError(f"{where}: no images")
    t = np.sort(s.times(where), kind="stable")
    twice = np.flatnonzero(np.diff(t) == 0)
    if twice.size:
        raise DatasetError(f"{where}: two images are stamped {t[twice[0]]} ns")
    return t


def _pairs(stamps: dict[str, np.ndarray], picked: dict[str, str | None], params: RosbagParams,
           bag: Path) -> Pairing:
    """The pairs used (the first ``max_frames``) and the unmatched images up to the last one
    (a warning when there are any)."""
    tol = int(round(params.pair_tolerance * NS))
    full = pair_stamps(stamps["left"], stamps["right"], tol)
    if not len(full.left):
        raise DatasetError(f"{bag}: no left image of {picked['left']} has a right image of "
                           f"{picked['right']} within {params.pair_tolerance * 1e3:g} ms")
    n = len(full.left) if params.max_frames is None else min(len(full.left), params.max_frames)
    last = stamps["left"][full.left[n - 1]] + tol
    pairing = Pairing(full.left[:n], full.right[:n],
                      full.unmatched_left[full.unmatched_left <= last],
                      full.unmatched_right[full.unmatched_right <= last])
    lone = np.concatenate([pairing.unmatched_left, pairing.unmatched_right])
    if lone.size:
        warnings.warn(f"{bag}: {len(pairing.unmatched_left)} left image(s) of {picked['left']} "
                      f"and {len(pairing.unmatched_right)} right image(s) of {picked['right']} "
                      f"have no partner within {params.pair_tolerance * 1e3:g} ms and are not "
                      f"used (the first stamped {lone.min()} ns)", stacklevel=3)
    return pairing


def _mount(tree: TfTree, cam_frame: str, params: RosbagParams,
           bag: Path) -> tuple[np.ndarray, str]:
    """The raw left camera's mount and where it came from (see the module docstring)."""
    default, found_in = DEFAULT_MOUNT, "assumed: level, 1.65 m above the ground"
    for robot in ROBOT_FRAMES:
        found = tree.lookup(robot, cam_frame) if cam_frame else None
        if found is not None:
            default, found_in = found, f"/tf_static {robot} -> {cam_frame}"
            break
    mount = np.asarray(default if params.mount is None else params.mount(default), np.float64)
    if params.mount is not None and not np.array_equal(mount, default):
        return mount, "[rig]"
    if default is DEFAULT_MOUNT:
        warnings.warn(f"{bag}: the camera mount is not in the bag (no /tf_static from "
                      f"{' or '.join(ROBOT_FRAMES)} to {cam_frame or 'the camera'!r}): "
                      "assuming a level camera 1.65 m above the ground; give [rig] height and "
                      "pitch, or [rig] matrix", stacklevel=3)
    return mount, found_in


def _camera(info: Series, image_topic: str, where: str) -> CameraModel:
    if info.first is None:
        raise DatasetError(f"{where}: no CameraInfo message")
    cam = camera_model(info.first, where)
    if rectified_topic(image_topic):
        k = np.asarray(cam.p, float)[:, :3]
        return CameraModel(k, np.zeros(5), np.eye(3), cam.p, cam.size)
    return cam


def _to_robot(tree: TfTree, frame: str, cam_frame: str, t_robot_cam: np.ndarray) -> np.ndarray:
    """T_robot_frame: through the camera where /tf_static links ``frame`` to it; the identity
    (the frame's axes taken as the robot's) otherwise."""
    t_cam_frame = tree.lookup(cam_frame, frame) if frame and cam_frame else None
    return np.eye(4) if t_cam_frame is None else t_robot_cam @ t_cam_frame


class _Pairs:
    """Second pass: the images of pair ``t``, streamed from the bag in record order (images of
    later pairs wait in a buffer; those of no pair are skipped)."""

    def __init__(self, reader: Any, picked: dict[str, str | None],
                 wanted: dict[str, np.ndarray], zero_stamps: dict[str, bool], bag: Path):
        self.reader, self.bag, self.picked = reader, bag, picked
        self.want = {side: {int(s): t for t, s in enumerate(stamps)}
                     for side, stamps in wanted.items()}
        self.zero = zero_stamps
        topics = {picked["left"], picked["right"]}
        self.messages: Iterator = reader.messages(
            connections=[c for c in reader.connections if c.topic in topics])
        self.buffer: dict[tuple[str, int], tuple[Any, str, int]] = {}

    def __call__(self, t: int) -> tuple[np.ndarray, np.ndarray]:
        while ("left", t) not in self.buffer or ("right", t) not in self.buffer:
            try:
                conn, bag_ns, raw = next(self.messages)
            except StopIteration:
                raise DatasetError(f"{self.bag}: the images of pair {t} were not found on the "
                                   "second reading") from None
            msg = self.reader.deserialize(raw, conn.msgtype)
            for side in ("left", "right"):
                if conn.topic == self.picked[side]:
                    stamp = bag_ns if self.zero[side] else stamp_ns(msg)
                    if stamp in self.want[side]:
                        self.buffer[(side, self.want[side][stamp])] = (msg, conn.msgtype, stamp)
        images = []
        for side in ("left", "right"):
            msg, msgtype, stamp = self.buffer.pop((side, t))
            images.append(decode_image(msg, msgtype, f"{self.bag}: {self.picked[side]} image "
                                                     f"stamped {stamp} ns"))
        return images[0], images[1]


def rosbag_frontend(path: str | Path, params: RosbagParams = RosbagParams(), *,
                    progress: Callable[[int, int], None] | None = None) -> RosbagFrontEnd:
    """Run the stereo front-end over a bag (see the module docstring). Warns for unmatched
    images, an assumed camera mount, a gyro that is not still at the start, and ground truth
    that covers no frame. ``progress(done, total)`` follows the frames."""
    bag = Path(path)
    if params.max_frames is not None and params.max_frames < 1:
        raise DatasetError(f"max_frames must be at least 1, got {params.max_frames}")
    check_roles(params.topics)
    reader = _open(bag)
    try:
        picked = pick_topics(_topics(reader), dict(params.topics), str(bag))
        series, tree = _read(reader, picked, bag)
        where = {role: f"{bag}: {name}" for role, name in picked.items()}
        stamps = {side: _sorted_stamps(series[side], where[side]) for side in ("left", "right")}
        pairing = _pairs(stamps, picked, params, bag)
        ts, n = stamps["left"][pairing.left], len(pairing.left)
        left = _camera(series["left_info"], picked["left"], where["left_info"])
        right = _camera(series["right_info"], picked["right"], where["right_info"])
        rig = RectifiedRig.from_rectification(left, right, f"{where['left_info']} + "
                                              f"{picked['right_info']}")
        cam_frame = series["left_info"].frame or series["left"].frame
        t_robot_cam, mount_from = _mount(tree, cam_frame, params, bag)
        frames: dict[str, np.ndarray] = {}

        def to_robot(frame: str) -> np.ndarray:
            if frame not in frames:
                frames[frame] = _to_robot(tree, frame, cam_frame, t_robot_cam)
            return frames[frame]

        period = int(np.median(np.diff(ts))) if n > 1 else 0
        slack, gap = max(period // 2, 5_000_000), int(params.pose_gap * NS)
        aids = SensorAids()
        if picked["imu"] and series["imu"].values:
            aids = imu_aids(series["imu"], to_robot(series["imu"].frame)[:3, :3], ts, period,
                            where["imu"], params.gravity_window, params.gyro_still,
                            params.max_gyro_bias, params.frontend.tilt_gate)
        if picked["wheel"] and series["wheel"].values:
            odom = planar_poses(series["wheel"], to_robot, where["wheel"], ts, gap, slack)
            wheel = increments_2d(odom)
            wheel[1:][~np.isfinite(odom[:-1]).all(axis=1)] = np.nan
            aids = aids._replace(wheel=wheel)
        gt, first_gt = None, 0
        if picked["ground_truth"] and series["ground_truth"].values:
            gt = planar_poses(series["ground_truth"], to_robot, where["ground_truth"], ts, gap,
                              slack)
            covered = np.flatnonzero(np.isfinite(gt).all(axis=1))
            if not covered.size:
                warnings.warn(f"{where['ground_truth']}: the ground truth covers none of the "
                              f"{n} frames; the run has no ground truth", stacklevel=2)
                gt = None
            else:
                first_gt = int(covered[0])
        t_rect = make_transform(np.asarray(rig.r_left, float).T, np.zeros(3))
        zero = {side: not any(series[side].stamps) for side in ("left", "right")}
        wanted = {"left": ts, "right": stamps["right"][pairing.right]}
        result = run_frontend(_Pairs(reader, picked, wanted, zero, bag), n, rig,
                              t_robot_cam @ t_rect, (ts - ts[0]) * 1e-9, params.frontend,
                              aids=aids, ground_truth=gt,
                              initial_pose=None if gt is None else gt[first_gt],
                              source=str(bag), progress=progress, time_origin_ns=int(ts[0]))
    finally:
        reader.close()
    return RosbagFrontEnd(result, picked, pairing, rig, mount_from)


def load_rosbag(path: str | Path, params: RosbagParams = RosbagParams()) -> Run:
    """The Run of a bag (see :func:`rosbag_frontend`)."""
    return rosbag_frontend(path, params).result.run


def _given(topics: tuple[tuple[str, str], ...]) -> dict[str, str | None]:
    given: dict[str, str | None] = {}
    for role, name in topics:
        if role in given:
            raise ConfigError(f"--topic {role}= is given twice")
        given[role] = name or None
    check_roles(given)
    return given


def _load(src: Source, config: Config, progress: Callable[[int, int], None] | None = None
          ) -> LoadedSource:
    where = f"--source rosbag {src.path}"
    default = FrontEndParams(stereo=DenseStereoParams(num_disparities=0))  # from the calibration
    params = RosbagParams(
        topics=_given(src.topics), max_frames=src.max_frames,
        frontend=FrontEndParams(local_map=localmap_params(config, "stereo"),
                                on_bad_frame=src.on_bad_frame,
                                stereo=stereo_settings(config, default.stereo)),
        mount=lambda found: camera_mount(config, found, where))
    out = rosbag_frontend(src.path, params, progress=progress)
    print(out.text())
    return LoadedSource(out.result.run, f"ROS bag {src.path}")


SOURCE = DataSource(name="rosbag", help="a ROS 1 or ROS 2 bag (rosbags library: the rosbag "
                    "extra)", load=_load, images=True, topics=True,
                    path="the bag: a ROS 1 .bag file, or a ROS 2 bag folder or its .db3/.mcap "
                    "file")
