"""Maps built from a Run's local maps at given poses: the local maps fused by the conjugate
update (eq. 14) on a lattice that holds them, e.g. the VO-only map (paper 7.1) or the map a
path implies. All NumPy, float64.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from gslam_jax.gridmap.grid import GridMap, turn_poses
from gslam_jax.rbpf import cells
from gslam_jax.run import Run

__all__ = ["pose_map", "pose_lattice", "place_local_map", "vo_only_map", "local_cell_centres"]


def pose_map(run: Run, poses: np.ndarray, margin: float = 2.0,
             lattice: GridMap | None = None) -> GridMap:
    """Fuse every local map of ``run`` at ``poses`` [T, 3] (one pose per frame) by the conjugate
    update (eq. 14: (k, S) add up), each local cell dropped into the nearest global cell.

    The map lies on ``lattice`` (its origin, shape, resolution and heading; its k and S are not
    used),
    by default one that covers every pose plus the local-map half-width and ``margin`` metres.
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.shape != (run.num_frames, 3):
        raise ValueError(f"poses must have shape [{run.num_frames}, 3], got {poses.shape}")
    if lattice is None:
        lattice = pose_lattice(run, poses, margin)
    k_map = np.zeros(lattice.k.size)
    s_map = np.zeros_like(k_map)
    for t in np.flatnonzero(run.obs_index >= 0):
        flat, k, S = place_local_map(run, t, poses[t], lattice)
        # unbuffered adds: work in the local map's cells, not in the lattice's (a bincount
        # with minlength would allocate the whole lattice at every frame)
        np.add.at(k_map, flat, k)
        np.add.at(s_map, flat, S)
    return lattice._replace(k=k_map.reshape(lattice.shape), S=s_map.reshape(lattice.shape))


def pose_lattice(run: Run, poses: np.ndarray, margin: float = 2.0) -> GridMap:
    """An empty map (k = S = 0) on the lattice that holds every local map of ``run`` placed at
    ``poses`` [T, 3]: every pose plus the local-map half-width and ``margin`` metres."""
    res = float(run.resolution)
    half = 0.5 * run.local_maps.shape[1] * res * math.sqrt(2.0) + margin
    lo = np.floor((poses[:, :2].min(0) - half) / res) * res
    hi = poses[:, :2].max(0) + half
    shape = tuple(int(v) for v in np.ceil((hi - lo) / res))
    return GridMap(np.zeros(shape), np.zeros(shape), (float(lo[0]), float(lo[1])), res)


@functools.lru_cache(maxsize=8)
def local_cell_centres(L: int, res: float) -> tuple[np.ndarray, np.ndarray]:
    """x, y [L, L] of a local map's cell centres in the robot frame (computed once per shape,
    not once per frame)."""
    centres = (np.arange(L) - L // 2 + 0.5) * res
    cx, cy = np.meshgrid(centres, centres, indexing="ij")
    cx.flags.writeable = cy.flags.writeable = False  # shared between calls
    return cx, cy


def place_local_map(run: Run, t: int, pose: np.ndarray, lattice: GridMap
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame ``t``'s local map placed at ``pose`` [3] on ``lattice`` (``pose_lattice``): the flat
    index of the lattice cell each of its known cells falls in (nearest cell centre), and
    their k and S. The local map's own lattice is turned by its ``Run.lattice_headings``; a
    turned map lattice (``GridMap.heading``) takes the pose on its axes."""
    res = lattice.resolution
    pose = turn_poses(pose, -lattice.heading)
    cx, cy = local_cell_centres(run.local_maps.shape[1], res)
    index = int(run.obs_index[t])
    k, S = np.moveaxis(cells.obs_from_stats(run.local_maps[index]), -1, 0)
    m = k > 0
    x, y, th = pose
    if run.lattice_headings is not None:
        th = th + float(run.lattice_headings[index])
    c, s = math.cos(th), math.sin(th)
    wx = x + c * cx[m] - s * cy[m]
    wy = y + s * cx[m] + c * cy[m]
    i = np.floor((wx - lattice.origin[0]) / res).astype(np.int64)
    j = np.floor((wy - lattice.origin[1]) / res).astype(np.int64)
    return i * lattice.shape[1] + j, np.asarray(k[m]), np.asarray(S[m])


def vo_only_map(run: Run, margin: float = 2.0) -> GridMap:
    """The VO-only map (paper 7.1): local maps fused at the poses integrated from the controls."""
    return pose_map(run, run.vo_poses(), margin)
