"""VO failure handling (paper section 4): wheel + IMU fallback, slip ratio, gravity tilt correction.

"When VO fails, the filter falls back on the wheel encoders and IMU to estimate the frame-to-frame
motion"; "the vehicle tilt estimate is continuously corrected using the gravity vector sensed by
the IMU ... a gate on the magnitude of the acceleration to find constant-velocity segments, then
slowly rotates the vehicle attitude to align it with the gravity vector."
"""

from __future__ import annotations

import numpy as np

from gslam_jax.vo.geometry import make_transform, rotvec_to_matrix

__all__ = ["SOURCES", "fallback_increment", "slip_ratio", "level_rotation", "correct_tilt",
           "planar_transform", "GRAVITY"]

GRAVITY = 9.80665
SOURCES = ("vo", "wheel", "wheel+imu", "imu", "hold")


def fallback_increment(previous: np.ndarray, wheel: np.ndarray | None,
                       imu_yaw: float | None) -> tuple[np.ndarray, str]:
    """Increment (dx, dy, dtheta) for a frame whose VO failed, and the name of its source.

    Translation comes from the wheel odometry increment when present; heading from the IMU yaw
    increment when present, else from the wheels. Without wheels the translation of the previous
    frame is held (constant-velocity assumption, source "imu" or "hold").
    """
    prev = np.asarray(previous, dtype=np.float64)
    if wheel is not None and np.all(np.isfinite(wheel)):
        u = np.array(wheel, dtype=np.float64)
        if imu_yaw is not None and np.isfinite(imu_yaw):
            u[2] = imu_yaw
            return u, "wheel+imu"
        return u, "wheel"
    u = prev.copy()
    if imu_yaw is not None and np.isfinite(imu_yaw):
        u[2] = imu_yaw
        return u, "imu"
    return u, "hold"


def slip_ratio(s_wheel: np.ndarray, s_vo: np.ndarray, min_speed: float = 1e-3) -> np.ndarray:
    """(s_wheel - s_vo) / |s_wheel| (paper section 4); NaN where the wheels barely turn."""
    s_wheel = np.asarray(s_wheel, dtype=np.float64)
    s_vo = np.asarray(s_vo, dtype=np.float64)
    out = np.full(np.broadcast(s_wheel, s_vo).shape, np.nan)
    moving = np.abs(s_wheel) >= min_speed
    out[moving] = ((s_wheel - s_vo)[moving]) / np.abs(s_wheel[moving])
    return out


def level_rotation(r_world_body: np.ndarray) -> np.ndarray:
    """The roll/pitch part of an attitude: R_yaw^T R, which maps body vectors to the level frame."""
    yaw = np.arctan2(r_world_body[1, 0], r_world_body[0, 0])
    c, s = np.cos(yaw), np.sin(yaw)
    r_yaw = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return r_yaw.T @ r_world_body


def correct_tilt(r_world_body: np.ndarray, accel_body: np.ndarray, gain: float = 0.05,
                 gate: float = 0.3) -> tuple[np.ndarray, bool]:
    """Nudge an attitude so the measured specific force points up; heading is left alone.

    ``accel_body`` is the accelerometer reading (m/s^2, body frame; at rest it points up with
    magnitude g). Only when ||a| - g| < ``gate`` (a constant-velocity segment) the attitude is
    rotated by ``gain`` times the angle between the measured and the true up direction, about a
    horizontal axis. Returns the new attitude and whether a correction was applied.
    """
    a = np.asarray(accel_body, dtype=np.float64)
    norm = float(np.linalg.norm(a))
    if not np.isfinite(norm) or abs(norm - GRAVITY) >= gate:
        return r_world_body, False
    up_meas = r_world_body @ (a / norm)  # where the body thinks "up" is, in world axes
    axis = np.cross(up_meas, [0.0, 0.0, 1.0])  # horizontal: rotation keeps the heading
    sin, cos = np.linalg.norm(axis), float(up_meas[2])
    if sin < 1e-12:
        return r_world_body, True
    angle = np.arctan2(sin, cos)
    return rotvec_to_matrix(axis / sin * angle * gain) @ r_world_body, True


def planar_transform(u: np.ndarray) -> np.ndarray:
    """4x4 robot-frame transform of a planar increment (dx, dy, dtheta)."""
    c, s = np.cos(u[2]), np.sin(u[2])
    return make_transform(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), [u[0], u[1], 0.0])
