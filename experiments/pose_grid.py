"""The offset grid of the pose objective (``experiments.pose_objective``) and what is read off
a score over it: the peak, and the information per axis at the peak and at the grid's scale.
Pure NumPy; the robot-frame axes are along-track, across-track (metres) and heading (rad)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

AXES = ("along", "across", "heading")
HEADING_TOL = 0.01  # rad: a peak "at the truth" lies within one cell and this of it


class Grid(NamedTuple):
    """Offsets per axis (robot frame: metres along and across track, radians), each symmetric
    about 0 and holding it."""

    along: np.ndarray
    across: np.ndarray
    heading: np.ndarray

    @property
    def steps(self) -> np.ndarray:
        return np.array([a[1] - a[0] if a.size > 1 else 1.0 for a in self])


def offset_grid(span_m: float, step_m: float, span_rad: float, step_rad: float) -> Grid:
    """Offsets k * step for |k * step| <= span (+ rounding), per axis."""
    def axis(span: float, step: float) -> np.ndarray:
        n = int(np.floor(span / step + 1e-9))
        return step * np.arange(-n, n + 1, dtype=np.float64)

    xy = axis(span_m, step_m)
    return Grid(xy, xy.copy(), axis(span_rad, step_rad))


def peak(scores: np.ndarray, grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """Grid index [3] of the maximum (ties: the tied offset nearest the truth, in steps) and
    its offset [3]."""
    steps = grid.steps
    offsets = np.stack(np.meshgrid(*grid, indexing="ij"), -1) / steps
    dist = np.where(scores == scores.max(), np.sum(offsets ** 2, -1), np.inf)
    index = np.array(np.unravel_index(np.argmin(dist), scores.shape))
    return index, np.array([axis[i] for axis, i in zip(grid, index)])


def information(scores: np.ndarray, index: np.ndarray, grid: Grid) -> np.ndarray:
    """-second difference / step^2 of ``scores`` per axis at ``index`` (moved to the nearest
    interior point on an axis where it lies on the edge; NaN on an axis of < 3 points)."""
    out = np.full(3, np.nan)
    for a, step in enumerate(grid.steps):
        n = scores.shape[a]
        if n < 3:
            continue
        i = index.copy()
        i[a] = min(max(i[a], 1), n - 2)
        lo, hi = i.copy(), i.copy()
        lo[a] -= 1
        hi[a] += 1
        out[a] = -(scores[tuple(lo)] - 2 * scores[tuple(i)] + scores[tuple(hi)]) / step ** 2
    return out


def fitted_information(scores: np.ndarray, grid: Grid) -> np.ndarray:
    """-2 x the quadratic coefficient of a least-squares parabola fitted to ``scores`` along
    each axis through the grid's centre (the truth), per axis (NaN on an axis of < 3 points)."""
    centre = tuple(len(a) // 2 for a in grid)
    out = np.full(3, np.nan)
    for a, x in enumerate(grid):
        if len(x) < 3:
            continue
        index = list(centre)
        index[a] = slice(None)
        out[a] = -2.0 * np.polyfit(x, scores[tuple(index)], 2)[0]
    return out
