"""Driving a course: a speed profile along the path, sampled into ground-truth poses per frame.

The robot (a LAGR-like differential drive) follows the path tangent, at most ``max_speed``
(<= 1 m/s), slowed in turns by limits on lateral acceleration and yaw rate, with bounded
acceleration, and stops for a few seconds at each survey point (and at the start).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gslam_jax.sim.courses import Course

__all__ = ["DriveParams", "Trajectory", "drive"]


@dataclass(frozen=True)
class DriveParams:
    rate_hz: float = 5.0
    max_speed: float = 0.8  # m/s
    max_lateral_accel: float = 0.25  # m/s^2
    max_yaw_rate: float = 0.5  # rad/s
    max_accel: float = 0.3  # m/s^2, also braking
    survey_dwell: float = 3.0  # s stopped at each survey point
    start_dwell: float = 2.0  # s stopped before moving

    def __post_init__(self) -> None:
        if not 0 < self.max_speed <= 1.0:
            raise ValueError(f"max_speed must be in (0, 1] m/s, got {self.max_speed}")
        if not 1.0 <= self.rate_hz <= 30.0:
            raise ValueError(f"rate_hz must be in [1, 30], got {self.rate_hz}")


@dataclass
class Trajectory:
    """Ground truth at every frame.

    timestamps: [T] s; poses: [T, 3] (x, y, theta) with theta unwrapped; s: [T] arc length;
    survey_frames: frame indices at which the robot is stopped at a survey point.
    """

    timestamps: np.ndarray
    poses: np.ndarray
    s: np.ndarray
    survey_frames: np.ndarray

    @property
    def num_frames(self) -> int:
        return int(self.timestamps.size)


def _speed_profile(course: Course, p: DriveParams) -> np.ndarray:
    s, heading = course.s, course.heading
    ds = np.diff(s)
    curv = np.abs(np.gradient(heading, s))
    # average curvature over ~0.25 m so a single kink does not stall the robot
    k = max(int(0.25 / max(np.median(ds), 1e-6)), 1)
    curv = np.convolve(curv, np.ones(k) / k, mode="same")
    v = np.full(s.shape, p.max_speed)
    with np.errstate(divide="ignore"):
        v = np.minimum(v, np.sqrt(p.max_lateral_accel / np.maximum(curv, 1e-9)))
        v = np.minimum(v, p.max_yaw_rate / np.maximum(curv, 1e-9))
    stops = np.searchsorted(s, course.survey_s).clip(0, s.size - 1)
    v[stops] = 0.0
    v[0] = v[-1] = 0.0
    for i in range(1, s.size):  # acceleration limit, forward then backward
        v[i] = min(v[i], np.sqrt(v[i - 1] ** 2 + 2 * p.max_accel * ds[i - 1]))
    for i in range(s.size - 2, -1, -1):
        v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2 * p.max_accel * ds[i]))
    return v


def drive(course: Course, params: DriveParams | None = None) -> Trajectory:
    """Time-parametrise ``course`` and sample ground-truth poses at ``params.rate_hz``."""
    p = params or DriveParams()
    s = course.s
    v = _speed_profile(course, p)
    dt = 2.0 * np.diff(s) / np.maximum(v[:-1] + v[1:], 1e-6)
    t = np.concatenate([[0.0], np.cumsum(dt)]) + p.start_dwell
    stop_idx = np.unique(np.searchsorted(s, course.survey_s[1:-1]).clip(1, s.size - 2))
    # insert the dwell at every intermediate survey stop: duplicate the knot with a later time
    t_knots, s_knots = [np.array([0.0])], [np.array([0.0])]
    prev, shift = 0, 0.0
    for i in stop_idx:
        t_knots.append(t[prev:i + 1] + shift)
        s_knots.append(s[prev:i + 1])
        shift += p.survey_dwell
        prev = i
    t_knots.append(t[prev:] + shift)
    s_knots.append(s[prev:])
    tk, sk = np.concatenate(t_knots), np.concatenate(s_knots)
    tk = np.maximum.accumulate(tk + np.arange(tk.size) * 1e-9)  # strictly increasing
    t_end = tk[-1] + p.survey_dwell
    times = np.arange(0.0, t_end, 1.0 / p.rate_hz)
    sf = np.interp(times, tk, sk)
    poses = np.stack([np.interp(sf, s, course.path[:, 0]), np.interp(sf, s, course.path[:, 1]),
                      np.interp(sf, s, course.heading)], axis=1)
    # survey frames: the middle frame of each stop (start, intermediate survey points, end)
    stops_s = np.concatenate([[s[0]], s[stop_idx], [s[-1]]])
    survey_frames = []
    for s_stop in stops_s:
        near = np.flatnonzero(np.abs(sf - s_stop) < 1e-6)
        if near.size:
            survey_frames.append(int(near[near.size // 2]))
    return Trajectory(timestamps=times, poses=poses, s=sf,
                      survey_frames=np.asarray(sorted(set(survey_frames)), dtype=np.int64))
