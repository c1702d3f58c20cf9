"""Write small ROS 1 / ROS 2 (sqlite3, MCAP) bags with ``rosbags``' writers, for the rosbag
source's tests: images, CameraInfo, odometry, IMU, poses and static transforms."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from gslam_jax.vo.calib import CameraModel

FORMATS = ("ros1", "sqlite3", "mcap")


def matrix_quaternion(r: np.ndarray) -> tuple[float, float, float, float]:
    """(w, x, y, z) of a rotation matrix (Shepperd's method, the largest pivot)."""
    r = np.asarray(r, float)
    tr = np.trace(r)
    cand = [tr, r[0, 0], r[1, 1], r[2, 2]]
    i = int(np.argmax(cand))
    if i == 0:
        s = 2.0 * np.sqrt(1.0 + tr)
        q = (s / 4, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s)
    elif i == 1:
        s = 2.0 * np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = ((r[2, 1] - r[1, 2]) / s, s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s)
    elif i == 2:
        s = 2.0 * np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = ((r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s)
    else:
        s = 2.0 * np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = ((r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4)
    return tuple(float(v) for v in q)


class BagWriter:
    """``with BagWriter(path, fmt) as w: w.image(...)``; ``fmt`` one of ``FORMATS``."""

    def __init__(self, path: Path, fmt: str) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.ros1 = fmt == "ros1"
        self.store = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.ROS2_HUMBLE)
        if self.ros1:
            from rosbags.rosbag1 import Writer

            self.writer = Writer(path)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
            self.writer = Writer(path, version=9, storage_plugin=plugin)
        self.conns: dict[str, Any] = {}
        self.t = self.store.types

    def __enter__(self) -> "BagWriter":
        self.writer.open()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.writer.close()

    def write(self, topic: str, msgtype: str, msg: Any, ns: int) -> None:
        if topic not in self.conns:
            self.conns[topic] = self.writer.add_connection(topic, msgtype, typestore=self.store)
        data = (self.store.serialize_ros1(msg, msgtype) if self.ros1
                else self.store.serialize_cdr(msg, msgtype))
        self.writer.write(self.conns[topic], ns, data)

    def header(self, ns: int, frame: str) -> Any:
        stamp = self.t["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
        header = self.t["std_msgs/msg/Header"]
        return (header(seq=0, stamp=stamp, frame_id=frame) if self.ros1
                else header(stamp=stamp, frame_id=frame))

    def image(self, topic: str, ns: int, img: np.ndarray, frame: str = "cam",
              encoding: str = "mono8", bag_ns: int | None = None) -> None:
        """``img`` grey; written as mono8, rgb8/bgr8 (grey in every channel) or mono16."""
        h, w = img.shape
        if encoding in ("rgb8", "bgr8"):
            data = np.repeat(img[:, :, None], 3, axis=2)
        elif encoding == "mono16":
            data = img.astype("<u2") * 257
        else:
            data = img
        raw = np.frombuffer(np.ascontiguousarray(data).tobytes(), np.uint8)
        msg = self.t["sensor_msgs/msg/Image"](
            header=self.header(ns, frame), height=h, width=w, encoding=encoding,
            is_bigendian=0, step=raw.size // h, data=raw)
        self.write(topic, "sensor_msgs/msg/Image", msg, ns if bag_ns is None else bag_ns)

    def compressed(self, topic: str, ns: int, img: np.ndarray | bytes, frame: str = "cam",
                   fmt: str = "png") -> None:
        data = img if isinstance(img, bytes) else cv2.imencode(f".{fmt}", img)[1].tobytes()
        msg = self.t["sensor_msgs/msg/CompressedImage"](
            header=self.header(ns, frame), format=fmt, data=np.frombuffer(data, np.uint8))
        self.write(topic, "sensor_msgs/msg/CompressedImage", msg, ns)

    def camera_info(self, topic: str, ns: int, cam: CameraModel, frame: str = "cam") -> None:
        names = ("D", "K", "R", "P") if self.ros1 else ("d", "k", "r", "p")
        values = [np.asarray(v, np.float64).ravel() for v in (cam.d, cam.k, cam.r, cam.p)]
        roi = self.t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0,
                                                         width=0, do_rectify=False)
        msg = self.t["sensor_msgs/msg/CameraInfo"](
            header=self.header(ns, frame), height=cam.size[1], width=cam.size[0],
            distortion_model=cam.distortion_model, binning_x=0, binning_y=0, roi=roi,
            **dict(zip(names, values)))
        self.write(topic, "sensor_msgs/msg/CameraInfo", msg, ns)

    def _pose(self, m: np.ndarray) -> Any:
        w, x, y, z = matrix_quaternion(m[:3, :3])
        return self.t["geometry_msgs/msg/Pose"](
            position=self.t["geometry_msgs/msg/Point"](x=m[0, 3], y=m[1, 3], z=m[2, 3]),
            orientation=self.t["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w))

    def _vector(self, v: np.ndarray) -> Any:
        return self.t["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def pose(self, topic: str, ns: int, m: np.ndarray, frame: str = "map") -> None:
        msg = self.t["geometry_msgs/msg/PoseStamped"](header=self.header(ns, frame),
                                                      pose=self._pose(m))
        self.write(topic, "geometry_msgs/msg/PoseStamped", msg, ns)

    def odometry(self, topic: str, ns: int, m: np.ndarray, frame: str = "odom",
                 child: str = "base_footprint") -> None:
        cov = np.zeros(36)
        msg = self.t["nav_msgs/msg/Odometry"](
            header=self.header(ns, frame), child_frame_id=child,
            pose=self.t["geometry_msgs/msg/PoseWithCovariance"](pose=self._pose(m),
                                                                covariance=cov),
            twist=self.t["geometry_msgs/msg/TwistWithCovariance"](
                twist=self.t["geometry_msgs/msg/Twist"](linear=self._vector(np.zeros(3)),
                                                        angular=self._vector(np.zeros(3))),
                covariance=cov))
        self.write(topic, "nav_msgs/msg/Odometry", msg, ns)

    def imu(self, topic: str, ns: int, gyro: np.ndarray, acc: np.ndarray,
            frame: str = "imu") -> None:
        cov = np.zeros(9)
        msg = self.t["sensor_msgs/msg/Imu"](
            header=self.header(ns, frame),
            orientation=self.t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=cov, angular_velocity=self._vector(gyro),
            angular_velocity_covariance=cov, linear_acceleration=self._vector(acc),
            linear_acceleration_covariance=cov)
        self.write(topic, "sensor_msgs/msg/Imu", msg, ns)

    def tf_static(self, ns: int, transforms: list[tuple[str, str, np.ndarray]]) -> None:
        """(parent, child, T_parent_child) each, on /tf_static."""
        self.write("/tf_static", "tf2_msgs/msg/TFMessage", self.tf_message(ns, transforms), ns)

    def tf_message(self, ns: int, transforms: list[tuple[str, str, np.ndarray]]) -> Any:
        """The TFMessage of (parent, child, T_parent_child) each (ROS 2 only: the ROS 1
        typestore has no tf2_msgs)."""
        items = []
        for parent, child, m in transforms:
            w, x, y, z = matrix_quaternion(m[:3, :3])
            items.append(self.t["geometry_msgs/msg/TransformStamped"](
                header=self.header(ns, parent), child_frame_id=child,
                transform=self.t["geometry_msgs/msg/Transform"](
                    translation=self._vector(m[:3, 3]),
                    rotation=self.t["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w))))
        return self.t["tf2_msgs/msg/TFMessage"](transforms=items)
