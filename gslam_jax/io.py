"""Trajectory files in the TUM and KITTI text formats, and map archives."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["write_tum", "write_kitti", "read_tum", "save_map"]


def write_tum(path: str | Path, timestamps: np.ndarray, poses: np.ndarray,
              origin_ns: int | None = None) -> None:
    """TUM RGB-D format: ``t x y z qx qy qz qw`` per line; planar poses (z = 0, yaw only).

    ``origin_ns``: the dataset clock's time of timestamp 0 in integer nanoseconds (EuRoC); the
    times written are then that clock's, in seconds with all nine decimals exact (float64
    seconds since 1970 would round them by up to 0.2 us)."""
    poses = np.asarray(poses, dtype=np.float64)
    half = 0.5 * poses[:, 2]
    rows = np.column_stack([poses[:, 0], poses[:, 1], np.zeros(len(poses)),
                            np.zeros(len(poses)), np.zeros(len(poses)), np.sin(half),
                            np.cos(half)])
    t = np.asarray(timestamps, np.float64)
    if origin_ns is None:
        times = [f"{v:.9f}" for v in t]
    else:
        ns = int(origin_ns) + np.round(t * 1e9).astype(np.int64)
        times = [f"{v // 10**9}.{v % 10**9:09d}" for v in ns.tolist()]
    with open(path, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n")
        for stamp, row in zip(times, rows):
            f.write(stamp + " " + " ".join(f"{v:.9f}" for v in row) + "\n")


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of ``write_tum`` for planar poses: (timestamps [T], poses [T, 3])."""
    rows = np.loadtxt(path, ndmin=2)
    yaw = 2.0 * np.arctan2(rows[:, 6], rows[:, 7])
    return rows[:, 0], np.column_stack([rows[:, 1], rows[:, 2], yaw])


def write_kitti(path: str | Path, poses: np.ndarray) -> None:
    """KITTI odometry's file layout: the first three rows of the 4x4 pose matrix per line.

    Only the layout is KITTI's, not its frame. The planar pose is written in the robot/world
    frame of this project (x forward, y left, z up; rotation about z by theta, z = 0), not in
    KITTI's camera frame (x right, y down, z forward) that ``poses/NN.txt`` uses, so KITTI's
    evaluation tools cannot compare this file with ``poses/NN.txt`` directly (``gslam run``
    writes it as ``trajectory_robot_kitti.txt``; on KITTI runs ``trajectory_kitti.txt`` holds
    the path in KITTI's camera frame, ``datasets.kitti.camera_poses``).
    """
    poses = np.asarray(poses, dtype=np.float64)
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    z = np.zeros(len(poses))
    o = np.ones(len(poses))
    rows = np.column_stack([c, -s, z, poses[:, 0], s, c, z, poses[:, 1], z, z, o, z])
    np.savetxt(path, rows, fmt="%.9e")


def save_map(path: str | Path, kmap: np.ndarray, smap: np.ndarray, origin: tuple[float, float],
             resolution: float, heading: float = 0.0, **extra: np.ndarray) -> None:
    """Variance grid map archive: k, S, origin (x, y of cell (0, 0)'s corner in the lattice's
    axes), resolution, heading (the lattice's axes in the map's frame, radians;
    ``gridmap.GridMap``).

    Axis 0 of the arrays runs along the lattice's x, axis 1 along its y.
    """
    np.savez_compressed(path, k=np.asarray(kmap, np.float32), S=np.asarray(smap, np.float32),
                        origin=np.asarray(origin, np.float64), resolution=np.float64(resolution),
                        heading=np.float64(heading), **extra)
