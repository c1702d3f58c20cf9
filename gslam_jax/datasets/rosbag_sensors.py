"""The non-image series of a bag for the rosbag source: poses (wheel odometry, ground truth)
interpolated at the frame times, and the IMU's specific force and gyro yaw per frame."""

from __future__ import annotations

import warnings
from typing import Any, Callable

import numpy as np

from gslam_jax.datasets.rosbag_msgs import frame_id, stamp_ns
from gslam_jax.vo.fallback import GRAVITY
from gslam_jax.vo.frontend import SensorAids
from gslam_jax.vo.geometry import invert, pose_to_2d

__all__ = ["Series", "interpolate_poses", "planar_poses", "imu_aids"]

NS = 1_000_000_000


class Series:
    """The messages of one topic as read: header stamps, record times, the first message and
    its frame, and a value per message."""

    def __init__(self) -> None:
        self.stamps: list[int] = []
        self.bag_times: list[int] = []
        self.frame = ""
        self.first: Any = None
        self.values: list[Any] = []

    def add(self, msg: Any, bag_ns: int, value: Any = None) -> None:
        if self.first is None:
            self.first, self.frame = msg, frame_id(msg.header.frame_id)
        self.stamps.append(stamp_ns(msg))
        self.bag_times.append(bag_ns)
        self.values.append(value)

    def times(self, where: str) -> np.ndarray:
        """Header stamps (ns); the bag's record times, with a warning, where all are zero."""
        if self.stamps and not any(self.stamps):
            warnings.warn(f"{where}: every header stamp is zero; using the bag's record times",
                          stacklevel=3)
            return np.array(self.bag_times, np.int64)
        return np.array(self.stamps, np.int64)


def interpolate_poses(t_ns: np.ndarray, poses_2d: np.ndarray, ts: np.ndarray, gap_ns: int,
                 slack_ns: int) -> np.ndarray:
    """[T, 3] planar poses at the frame times ``ts`` (linear, the yaw unwrapped); NaN outside
    the samples' span (beyond ``slack_ns``) and between samples more than ``gap_ns`` apart."""
    keep = np.all(np.isfinite(poses_2d), axis=1)
    t_ns, poses_2d = t_ns[keep], poses_2d[keep]
    out = np.full((len(ts), 3), np.nan)
    if not len(t_ns):
        return out
    order = np.argsort(t_ns, kind="stable")
    t_ns, poses_2d = t_ns[order], poses_2d[order]
    first = np.concatenate([[True], np.diff(t_ns) > 0])
    t_ns, poses_2d = t_ns[first], poses_2d[first]
    yaw = np.unwrap(poses_2d[:, 2])
    x = (t_ns - t_ns[0]).astype(np.float64)
    at = (ts - t_ns[0]).astype(np.float64)
    cols = [np.interp(at, x, poses_2d[:, 0]), np.interp(at, x, poses_2d[:, 1]),
            np.interp(at, x, yaw)]
    hi = np.clip(np.searchsorted(t_ns, ts), 0, len(t_ns) - 1)
    lo = np.clip(np.searchsorted(t_ns, ts, side="right") - 1, 0, len(t_ns) - 1)
    ok = ((ts >= t_ns[0] - slack_ns) & (ts <= t_ns[-1] + slack_ns)
          & ((t_ns[hi] - t_ns[lo]) <= gap_ns))
    out[ok] = np.stack(cols, axis=1)[ok]
    out[:, 2] = np.where(ok, np.angle(np.exp(1j * out[:, 2])), np.nan)
    return out


def planar_poses(s: Series, to_robot: Callable[[str], np.ndarray], where: str, ts: np.ndarray,
                 gap_ns: int, slack_ns: int) -> np.ndarray:
    """[T, 3] planar robot poses at the frame times ``ts`` of a pose series (values: 4x4 pose
    of a child frame, the child's name); ``to_robot(child)`` is T_robot_child."""
    poses = np.stack([pose_to_2d(m @ invert(to_robot(child))) if np.all(np.isfinite(m))
                      else np.full(3, np.nan) for m, child in s.values])
    return interpolate_poses(s.times(where), poses, ts, gap_ns, slack_ns)


def imu_aids(s: Series, r_robot_imu: np.ndarray, ts: np.ndarray, period: int, where: str,
             gravity_window: float, gyro_still: float, max_gyro_bias: float,
             tilt_gate: float) -> SensorAids:
    """Per frame ``ts`` (ns): the mean specific force since the previous frame (robot axes)
    and the gyro yaw increment, as the EuRoC adapter (``EurocParams`` for the still start and
    the bias); NaN for frames more than ``period`` outside the log and for gaps in it. Values:
    (gyro xyz, accelerometer xyz) in the IMU frame, turned by ``r_robot_imu``."""
    t_imu = s.times(where)
    order = np.argsort(t_imu, kind="stable")
    t_imu = t_imu[order]
    data = np.asarray(s.values, np.float64)[order]
    gyro, acc = data[:, :3] @ r_robot_imu.T, data[:, 3:] @ r_robot_imu.T
    first = (t_imu >= ts[0]) & (t_imu <= ts[0] + int(gravity_window * NS))
    still = first & (np.abs(np.linalg.norm(acc, axis=1) - GRAVITY) < tilt_gate)
    bias = gyro[still].mean(axis=0) if still.any() else np.full(3, np.nan)
    spread = float(np.linalg.norm(gyro[still].std(axis=0))) if still.any() else np.nan
    if spread < gyro_still and np.linalg.norm(bias) < max_gyro_bias:
        gyro = gyro - bias
    else:
        warnings.warn(f"{where}: the IMU is not still within {gravity_window} s of the "
                      f"first frame (gyro mean {np.linalg.norm(bias):.3f} rad/s, spread "
                      f"{spread:.3f} rad/s): no gyro bias removed", stacklevel=3)
    n = len(ts)
    accel, yaw = np.zeros((n, 3)), np.zeros(n)
    edges = np.searchsorted(t_imu, ts, side="right")
    for t in range(n):
        lo = edges[t - 1] if t else max(edges[0] - 1, 0)
        near = min(lo, len(t_imu) - 1)
        accel[t] = acc[near:max(edges[t], near + 1)].mean(axis=0)
        if t:
            start = max(lo - 1, 0)
            dt = np.diff(t_imu[start:edges[t]]) * 1e-9
            yaw[t] = float(np.sum(gyro[start + 1:edges[t], 2] * dt))
    outside = (ts < t_imu[0] - period) | (ts > t_imu[-1] + period)
    gap = np.concatenate([[False], (np.diff(edges) == 0) & (ts[1:] >= t_imu[0])
                          & (ts[:-1] < t_imu[-1])])
    accel[outside] = np.nan
    yaw[outside | gap | np.concatenate([[False], outside[:-1]])] = np.nan
    return SensorAids(accel=accel, imu_yaw=yaw)
