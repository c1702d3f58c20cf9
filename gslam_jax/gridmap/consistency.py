"""Is a run's map consistent with itself? Finding terrain that a run mapped twice.

A filter that loses its way and comes back to terrain it has mapped lays a second copy of that
terrain beside the first (walls doubled): the map is broken by its own run, and merging it, or
reusing it, spreads the error. Such a map can still align with another map at a stable wrong
placement (``gridmap.align``), so it has to be caught from the run itself.

The check reads the run's local maps at its reported path (the map's own poses). The path is cut
into stretches of ``stretch_m`` metres of travel. Each stretch's local maps, fused (eq. 14), are
scored against the map fused from every frame at least ``gap_m`` metres of travel before it (so
the terrain just driven does not count), by the gamma likelihood of ``gridmap.score`` (eq. 26,
each cell's term against chance, standardised to z), over every shift within ``search_m`` and
heading within ``search_rad`` of where the path placed it (turns about the stretch's centroid).
A stretch that lands on enough earlier cells is a revisit. The revisit is doubled when a
placement whose cells lie more than ``tolerance_m`` (RMS) from where the path put them scores
better than the path's own placement by at least ``min_gap_z`` in z, is itself well above chance
(``min_z``), and is not ambiguous (no distinct placement within ``min_gap_z`` of it). A
consistent map scores best at, or within a cell or two of, its own placement.

All NumPy apart from the scoring (``gridmap.score.score_poses``, jitted); deterministic.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from gslam_jax.gridmap.grid import GridMap, apply_pose, arc_length, known_cells
from gslam_jax.gridmap.pose_maps import place_local_map, pose_lattice
from gslam_jax.gridmap.score import score_poses
from gslam_jax.run import Run

__all__ = ["ConsistencyParams", "Revisit", "Consistency", "check_consistency"]


class ConsistencyParams(NamedTuple):
    """Settings of ``check_consistency`` (see the module)."""

    stretch_m: float = 10.0
    gap_m: float = 30.0
    search_m: float = 3.0
    search_rad: float = math.radians(6.0)
    tolerance_m: float = 1.0
    min_overlap: int = 200
    min_z: float = 12.0
    min_gap_z: float = 4.0
    max_dof: int = 8


class Revisit(NamedTuple):
    """One stretch that lands on earlier terrain: its frames (first, last), how many of its
    cells lie on earlier known cells as mapped, the z of the path's own placement and of the
    best one, the best placement's correction [3] (the stretch's frame moved by x, y, turned by
    theta, in the map frame), how far (RMS over the stretch's cells) it moves them, the z of the
    best distinct runner-up, and the verdict."""

    first_frame: int
    last_frame: int
    overlap: int
    z_as_mapped: float
    z_best: float
    correction: np.ndarray
    offset_m: float
    z_runner_up: float
    doubled: bool

    def summary(self) -> dict:
        return {"frames": [self.first_frame, self.last_frame], "overlap_cells": self.overlap,
                "z_as_mapped": self.z_as_mapped, "z_best": self.z_best,
                "correction": [float(v) for v in self.correction],
                "offset_m": self.offset_m, "z_runner_up": self.z_runner_up,
                "doubled": self.doubled}


class Consistency(NamedTuple):
    """Every revisit the check found, in order of travel."""

    revisits: list[Revisit]
    params: ConsistencyParams

    @property
    def doubled(self) -> list[Revisit]:
        return [r for r in self.revisits if r.doubled]

    @property
    def consistent(self) -> bool:
        return not self.doubled

    def summary(self) -> dict:
        return {"consistent": self.consistent, "revisits_checked": len(self.revisits),
                "doubled": [r.summary() for r in self.doubled],
                "worst_offset_m": max((r.offset_m for r in self.doubled), default=0.0),
                "settings": self.params._asdict()}

    def describe(self) -> str:
        """One line for a person: what was checked and what was found."""
        if self.consistent:
            return (f"map consistent with itself: {len(self.revisits)} revisited stretches "
                    "score best where the path placed them")
        worst = max(self.doubled, key=lambda r: r.offset_m)
        return (f"map NOT consistent with itself: {len(self.doubled)} of {len(self.revisits)} "
                f"revisited stretches fit the earlier map better elsewhere; worst: frames "
                f"{worst.first_frame}-{worst.last_frame}, {worst.offset_m:.2f} m off (z "
                f"{worst.z_best:.0f} against {worst.z_as_mapped:.0f} as mapped): the run "
                "mapped that terrain twice")


def _window(flat_k: np.ndarray, flat_s: np.ndarray, lattice: GridMap, i0: int, j0: int,
            side: int) -> GridMap:
    """The ``side`` x ``side`` cells of ``lattice`` from cell (i0, j0), zero (unknown) beyond it:
    one shape for every stretch."""
    H, W = lattice.shape
    k = np.zeros((side, side))
    S = np.zeros((side, side))
    r0, r1, c0, c1 = max(i0, 0), min(i0 + side, H), max(j0, 0), min(j0 + side, W)
    if r0 < r1 and c0 < c1:
        k[r0 - i0:r1 - i0, c0 - j0:c1 - j0] = flat_k.reshape(H, W)[r0:r1, c0:c1]
        S[r0 - i0:r1 - i0, c0 - j0:c1 - j0] = flat_s.reshape(H, W)[r0:r1, c0:c1]
    r = lattice.resolution
    return GridMap(k, S, (lattice.origin[0] + i0 * r, lattice.origin[1] + j0 * r), r)


def _grid(shifts: np.ndarray, headings: np.ndarray) -> np.ndarray:
    """Every pose (dx, dy, theta) [n, 3] from ``shifts`` (each axis) and ``headings``, heading
    slowest."""
    th, dx, dy = (v.ravel() for v in np.meshgrid(headings, shifts, shifts, indexing="ij"))
    return np.stack([dx, dy, th], -1)


def check_consistency(run: Run, poses: np.ndarray,
                      params: ConsistencyParams = ConsistencyParams(),
                      progress=None) -> Consistency:
    """The revisits of ``run`` whose local maps, placed at ``poses`` [T, 3] (the map's own path,
    e.g. ``SlamResult.path``), fit the earlier map better elsewhere (see the module).
    ``progress(i, n)``, when given, is called after each stretch."""
    poses = np.asarray(poses, np.float64)
    if poses.shape != (run.num_frames, 3):
        raise ValueError(f"poses must have shape [{run.num_frames}, 3], got {poses.shape}")
    lattice = pose_lattice(run, poses, margin=params.search_m + 1.0)
    res = lattice.resolution
    arc = arc_length(poses)
    frames = np.flatnonzero(np.asarray(run.obs_index) >= 0)
    stretch = np.floor(arc / params.stretch_m).astype(np.int64)
    earlier_k = np.zeros(lattice.k.size)
    earlier_s = np.zeros(lattice.k.size)
    added = 0  # frames[:added] are in the earlier map
    reach = 0.5 * run.local_maps.shape[1] * res * math.sqrt(2.0)  # a local map's half-diagonal
    half = 16 * int(math.ceil((0.5 * params.stretch_m + reach + params.search_m) / res / 16 + 1))
    revisits: list[Revisit] = []
    groups = [frames[stretch[frames] == s] for s in np.unique(stretch[frames])]
    for n, group in enumerate(groups):
        start = arc[group[0]]
        while added < len(frames) and arc[frames[added]] < start - params.gap_m:
            flat, k, S = place_local_map(run, frames[added], poses[frames[added]], lattice)
            np.add.at(earlier_k, flat, k)  # eq. 14, without a lattice-sized array per frame
            np.add.at(earlier_s, flat, S)
            added += 1
        if added:
            found = _check_stretch(run, poses, group, lattice, earlier_k, earlier_s, half,
                                   params)
            if found is not None:
                revisits.append(found)
        if progress is not None:
            progress(n + 1, len(groups))
    return Consistency(revisits, params)


def _check_stretch(run: Run, poses: np.ndarray, group: np.ndarray, lattice: GridMap,
                   earlier_k: np.ndarray, earlier_s: np.ndarray, half: int,
                   params: ConsistencyParams) -> Revisit | None:
    """The revisit verdict of one stretch (frames ``group``) against the earlier map, in a
    window of 2 ``half`` cells about it; None when it does not land on the earlier map."""
    k_b = np.zeros(lattice.k.size)
    s_b = np.zeros(lattice.k.size)
    for t in group:
        flat, k, S = place_local_map(run, t, poses[t], lattice)
        np.add.at(k_b, flat, k)
        np.add.at(s_b, flat, S)
    known = (k_b > 0).reshape(lattice.shape)
    rows_b, cols_b = np.flatnonzero(known.any(1)), np.flatnonzero(known.any(0))
    # one square window about the stretch for every stretch (the scorer compiles once per
    # shape): the stretch's reach (its travel and the local maps' half-diagonal) and the search
    ci, cj = (rows_b[0] + rows_b[-1]) // 2, (cols_b[0] + cols_b[-1]) // 2
    a = _window(earlier_k, earlier_s, lattice, ci - half, cj - half, 2 * half)
    if int(a.known.sum()) < params.min_overlap:
        return None
    b = _window(k_b, s_b, lattice, ci - half, cj - half, 2 * half)
    # in coordinates centred on the stretch's cells, where its headings turn
    world, _, _ = known_cells(b)
    centroid = world.mean(axis=0)
    a = a._replace(origin=(a.origin[0] - centroid[0], a.origin[1] - centroid[1]))
    b = b._replace(origin=a.origin)
    world = world - centroid
    radius = float(np.max(np.hypot(*world.T))) + b.resolution
    # The search: every placement on a grid of two cells and four heading steps (a step moves
    # a cell at the window's half-side by one cell), scored on 2 x 2 blocks
    # (``gridmap.score.pool``);
    # then, on the cells themselves, the neighbours (one cell, two heading steps) of its best
    # placement, of its best placement distinct from that, and the path's own placement (the
    # stretch's frame turns about its centroid: a pose is its own correction).
    res = b.resolution
    dth = min(1.0 / half, params.search_rad)
    n = 2 * int(math.ceil(params.search_m / (2 * res)))
    m = 4 * int(math.ceil(params.search_rad / (4 * dth)))
    coarse = _grid(res * np.arange(-n, n + 1, 2), dth * np.arange(-m, m + 1, 4))
    score, _, overlap = score_poses(a, b, coarse, factor=2, max_dof=params.max_dof, pad=0)
    if overlap.max() < params.min_overlap // 4:
        return None
    first = int(np.argmax(score))
    apart = _distinct(coarse, coarse[first], radius, params.tolerance_m)
    second = int(np.argmax(np.where(apart, score, -np.inf))) if apart.any() else first
    step = _grid(res * np.arange(-1, 2), dth * np.arange(-2, 3))
    poses = np.concatenate([np.zeros((1, 3)), coarse[first] + step, coarse[second] + step])
    _, z, overlap = score_poses(a, b, poses, max_dof=params.max_dof, pad=0)
    if overlap.max() < params.min_overlap:
        return None
    best = int(np.argmax(z))
    offset = float(np.sqrt(np.mean(np.sum((apply_pose(poses[best], world) - world) ** 2,
                                          axis=1))))
    apart = _distinct(poses, poses[best], radius, params.tolerance_m)
    z_runner = float(z[apart].max()) if apart.any() else -math.inf
    doubled = bool(offset > params.tolerance_m and z[best] >= params.min_z
                   and z[best] - z[0] >= params.min_gap_z
                   and z[best] - z_runner >= params.min_gap_z)
    return Revisit(int(group[0]), int(group[-1]), int(overlap[0]), float(z[0]),
                   float(z[best]), poses[best], offset, z_runner, doubled)


def _distinct(poses: np.ndarray, pose: np.ndarray, radius: float, tolerance: float
              ) -> np.ndarray:
    """[n] whether each of ``poses`` moves the stretch's cells (within ``radius`` of the
    centroid) by more than ``tolerance`` from where ``pose`` puts them (a bound: the shift plus
    the turn at the radius)."""
    return (np.hypot(*(poses[:, :2] - pose[:2]).T) + np.abs(poses[:, 2] - pose[2]) * radius
            > tolerance)
