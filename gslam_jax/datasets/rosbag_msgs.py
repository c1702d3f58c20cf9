"""ROS messages as arrays, for the rosbag source: header stamps, images, CameraInfo, poses and
the static transform tree (``/tf_static``).

Messages are those ``rosbags`` deserialises (attribute access, ROS 1 and ROS 2 alike; ROS 1's
CameraInfo spells ``K, D, R, P`` where ROS 2 spells ``k, d, r, p``). Nothing here opens a bag
or imports ``rosbags``.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import cv2
import numpy as np

from gslam_jax.datasets.reading import quat_to_matrix
from gslam_jax.vo.calib import CalibrationError, CameraModel, ImageError
from gslam_jax.vo.geometry import invert, make_transform

__all__ = ["IMAGE", "COMPRESSED", "CAMERA_INFO", "ODOMETRY", "IMU", "POSE", "TRANSFORM", "TF",
           "ENCODINGS", "stamp_ns", "decode_image", "camera_model", "pose_matrix", "frame_id",
           "TfTree"]

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
ODOMETRY = "nav_msgs/msg/Odometry"
IMU = "sensor_msgs/msg/Imu"
POSE = "geometry_msgs/msg/PoseStamped"
TRANSFORM = "geometry_msgs/msg/TransformStamped"
TF = "tf2_msgs/msg/TFMessage"

# sensor_msgs/Image encodings read: channels, bytes per channel, cv2 conversion to grey.
ENCODINGS: dict[str, tuple[int, int, int | None]] = {
    "mono8": (1, 1, None), "8uc1": (1, 1, None), "mono16": (1, 2, None), "16uc1": (1, 2, None),
    "rgb8": (3, 1, cv2.COLOR_RGB2GRAY), "bgr8": (3, 1, cv2.COLOR_BGR2GRAY),
    "rgba8": (4, 1, cv2.COLOR_RGBA2GRAY), "bgra8": (4, 1, cv2.COLOR_BGRA2GRAY)}


def stamp_ns(msg: Any) -> int:
    """The header stamp in nanoseconds."""
    stamp = msg.header.stamp
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def frame_id(name: str) -> str:
    """A tf frame name without ROS 1's leading '/'."""
    return str(name).lstrip("/")


def decode_image(msg: Any, msgtype: str, where: str) -> np.ndarray:
    """The grey uint8 image of a ``sensor_msgs/Image`` (``ENCODINGS``; 16-bit mono is scaled
    by 1/257, its full range to 0..255) or ``sensor_msgs/CompressedImage`` (``cv2.imdecode``).
    ImageError naming ``where`` (topic and stamp) for an unknown encoding or bad data."""
    data = np.frombuffer(memoryview(np.ascontiguousarray(msg.data)), np.uint8)
    if msgtype == COMPRESSED:
        img = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE) if data.size else None
        if img is None:
            raise ImageError(f"{where}: compressed image ({msg.format!r}) could not be decoded")
        return img
    enc = str(msg.encoding).lower()
    if enc not in ENCODINGS:
        raise ImageError(f"{where}: image encoding {msg.encoding!r} is not supported "
                         f"({', '.join(ENCODINGS)}, or a CompressedImage)")
    ch, size, conversion = ENCODINGS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h < 1 or w < 1 or step < w * ch * size or data.size < h * step:
        raise ImageError(f"{where}: {w}x{h} {enc} image with step {step} holds {data.size} "
                         f"bytes, expected {h} rows of at least {w * ch * size}")
    rows = data[:h * step].reshape(h, step)[:, :w * ch * size]
    if size == 2:
        pixels = rows.copy().view(">u2" if msg.is_bigendian else "<u2").reshape(h, w)
        return np.round(pixels / 257.0).astype(np.uint8)
    img = rows.reshape(h, w, ch) if ch > 1 else rows
    return np.ascontiguousarray(img) if conversion is None else cv2.cvtColor(img, conversion)


def _numbers(msg: Any, name: str) -> np.ndarray:
    """A CameraInfo matrix field by its ROS 2 (lower case) or ROS 1 (upper case) name."""
    value = getattr(msg, name.lower(), None)
    if value is None:
        value = getattr(msg, name.upper())
    return np.asarray(value, np.float64).ravel()


def camera_model(msg: Any, where: str) -> CameraModel:
    """The CameraModel of a ``sensor_msgs/CameraInfo`` (K, D, R, P, size, distortion model).
    CalibrationError naming ``where`` for an uncalibrated camera (K or P zero), binning or a
    region of interest (not supported), or a wrong field (``CameraModel.check``)."""
    k, d, r, p = (_numbers(msg, f) for f in ("K", "D", "R", "P"))
    for name, a, n in (("K", k, 9), ("R", r, 9), ("P", p, 12)):
        if a.size != n:
            raise CalibrationError(f"{where}: field {name!r} has {a.size} numbers, expected {n}")
        if name != "R" and not a.any():
            raise CalibrationError(f"{where}: field {name!r} is all zero: the camera is not "
                                   "calibrated")
    if not r.any():  # a monocular calibration leaves R unset: no rectifying rotation
        r = np.eye(3).ravel()
    if max(int(msg.binning_x), int(msg.binning_y)) > 1:
        raise CalibrationError(f"{where}: binning {msg.binning_x}x{msg.binning_y} is not "
                               "supported (give full-resolution images)")
    roi = msg.roi
    if int(roi.width) and (int(roi.width), int(roi.height)) != (int(msg.width), int(msg.height)):
        raise CalibrationError(f"{where}: a region of interest ({roi.width}x{roi.height} at "
                               f"{roi.x_offset}, {roi.y_offset}) is not supported")
    model = str(msg.distortion_model) or "plumb_bob"
    cam = CameraModel(k.reshape(3, 3), d, r.reshape(3, 3), p.reshape(3, 4),
                      (int(msg.width), int(msg.height)), model)
    cam.check(where)
    return cam


def _transform(translation: Any, rotation: Any) -> np.ndarray:
    q = np.array([rotation.w, rotation.x, rotation.y, rotation.z], np.float64)
    t = np.array([translation.x, translation.y, translation.z], np.float64)
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(t)) and np.linalg.norm(q) > 0):
        return np.full((4, 4), np.nan)
    return make_transform(quat_to_matrix(q), t)


def pose_matrix(msg: Any, msgtype: str) -> tuple[np.ndarray, str]:
    """4x4 pose and the child frame of a ``geometry_msgs/PoseStamped`` (child ''),
    ``nav_msgs/Odometry`` or ``geometry_msgs/TransformStamped``; NaN for an invalid one."""
    if msgtype == TRANSFORM:
        tr = msg.transform
        return _transform(tr.translation, tr.rotation), frame_id(msg.child_frame_id)
    pose = msg.pose.pose if msgtype == ODOMETRY else msg.pose
    child = frame_id(msg.child_frame_id) if msgtype == ODOMETRY else ""
    return _transform(pose.position, pose.orientation), child


class TfTree:
    """The static transforms of a bag (``tf2_msgs/TFMessage`` on ``/tf_static``) as an
    undirected tree; :meth:`lookup` composes the transforms along the path between two frames."""

    def __init__(self) -> None:
        self.edges: dict[str, list[tuple[str, np.ndarray]]] = {}

    def add(self, msg: Any) -> None:
        """Add the transforms of one TFMessage (parent ``header.frame_id``, child
        ``child_frame_id``; T_parent_child)."""
        for tr in msg.transforms:
            parent, child = frame_id(tr.header.frame_id), frame_id(tr.child_frame_id)
            t = _transform(tr.transform.translation, tr.transform.rotation)
            if parent and child and np.all(np.isfinite(t)):
                self.edges.setdefault(parent, []).append((child, t))
                self.edges.setdefault(child, []).append((parent, invert(t)))

    def __contains__(self, frame: str) -> bool:
        return frame in self.edges

    def lookup(self, target: str, source: str) -> np.ndarray | None:
        """T_target_source (the pose of ``source`` in ``target``; identity for the same frame),
        None when the tree does not link them."""
        if target == source:
            return np.eye(4)
        seen, todo = {target}, deque([(target, np.eye(4))])
        while todo:
            frame, t = todo.popleft()
            for nxt, t_step in self.edges.get(frame, []):
                if nxt == source:
                    return t @ t_step
                if nxt not in seen:
                    seen.add(nxt)
                    todo.append((nxt, t @ t_step))
        return None
