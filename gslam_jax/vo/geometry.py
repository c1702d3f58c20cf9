"""Rigid-body helpers for the stereo front-end (NumPy, float64).

Conventions: a transform ``T_ab`` is a 4x4 matrix mapping points in frame b to frame a
(``X_a = R X_b + t``); it is also the pose of frame b expressed in frame a. Cameras use the
OpenCV convention (x right, y down, z forward); the robot frame is x forward, y left, z up.
"""

from __future__ import annotations

import numpy as np

__all__ = ["rotvec_to_matrix", "matrix_to_rotvec", "make_transform", "invert", "rotation_angle",
           "yaw_of", "pose_to_2d", "increments_2d", "CAM_TO_ROBOT_AXES"]

# Columns are the camera axes (x right, y down, z forward) written in robot axes (x fwd, y left, z up).
CAM_TO_ROBOT_AXES = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def rotvec_to_matrix(w: np.ndarray) -> np.ndarray:
    """Rodrigues' formula for one rotation vector [3] -> [3, 3]."""
    w = np.asarray(w, dtype=np.float64)
    theta = float(np.linalg.norm(w))
    k = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if theta < 1e-12:
        return np.eye(3) + k
    k /= theta
    return np.eye(3) + np.sin(theta) * k + (1.0 - np.cos(theta)) * (k @ k)


def matrix_to_rotvec(r: np.ndarray) -> np.ndarray:
    """Inverse of :func:`rotvec_to_matrix` (angles below pi)."""
    cos = np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)
    theta = float(np.arccos(cos))
    v = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    if theta < 1e-9:
        return v / 2.0
    return v * theta / (2.0 * np.sin(theta))


def make_transform(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = r
    out[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return out


def invert(t_ab: np.ndarray) -> np.ndarray:
    r = t_ab[:3, :3]
    return make_transform(r.T, -r.T @ t_ab[:3, 3])


def rotation_angle(r: np.ndarray) -> float:
    """Angle of a rotation matrix, radians."""
    return float(np.arccos(np.clip((np.trace(r[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))


def yaw_of(r: np.ndarray) -> float:
    """Heading of a robot-frame rotation: direction of its x axis in the world x-y plane."""
    return float(np.arctan2(r[1, 0], r[0, 0]))


def pose_to_2d(t_wr: np.ndarray) -> np.ndarray:
    """Project a 6-DoF robot pose (robot axes, world z up) to (x, y, yaw)."""
    return np.array([t_wr[0, 3], t_wr[1, 3], yaw_of(t_wr[:3, :3])])


def increments_2d(poses_2d: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
    """Robot-frame increments u_t = (dx, dy, dtheta) between consecutive 2-D poses [T, 3].

    ``u_0`` moves from ``start`` (default: ``poses_2d[0]``, i.e. a zero first control) to frame 0,
    so integrating the increments from ``start`` reproduces the poses (the Run convention).
    """
    poses = np.asarray(poses_2d, dtype=np.float64)
    prev = np.vstack([poses[:1] if start is None else np.asarray(start)[None], poses[:-1]])
    c, s = np.cos(prev[:, 2]), np.sin(prev[:, 2])
    dx, dy = poses[:, 0] - prev[:, 0], poses[:, 1] - prev[:, 1]
    dth = np.angle(np.exp(1j * (poses[:, 2] - prev[:, 2])))
    return np.stack([c * dx + s * dy, -s * dx + c * dy, dth], axis=1)
