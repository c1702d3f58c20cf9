"""Loop closure as a measured verdict: did a trajectory estimate close the loop at a revisit?

A revisit is a pair of frames (i, j) where the true path comes back, after a loop of length L,
to within ``radius`` of where it was at i. The estimate closed that loop when both hold:

- revisit error <= tolerance (1 m): the position of j seen from the pose at i, in the estimate
  against the truth, ``|R(-th_i) (p_j - p_i) - R(-th'_i) (p'_j - p'_i)|`` (each path in its own
  frame at i, so any rigid motion of either path leaves it unchanged; a heading error at i
  counts only times the true gap |p'_j - p'_i| <= radius);
- map offset <= tolerance: the map is not doubled. The local maps of the frames within
  ``window`` metres of travel around i and around j are fused (eq. 14) at the estimated poses
  into two maps; the offset is the shift of the second that best matches the first (peak
  correlation of the expected standard deviation over the cells both know, searched on the
  cell grid within ``max_shift``, 3 m). A closed loop lays the revisited terrain over itself (offset
  near 0); an open one lays a second copy beside the first, as far off as its error. The
  fused map at the final best particle's path is that particle's map (its ancestry placed
  every local map it holds), so the check reads the filter's own map, split by visit.

All NumPy, float64; deterministic.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from scipy.signal import correlate
from scipy.special import gammaln

from gslam_jax.gridmap.grid import GridMap, arc_length
from gslam_jax.gridmap.pose_maps import pose_map
from gslam_jax.run import Run

__all__ = ["TOLERANCE", "Closure", "Revisit", "closure", "expected_std", "find_revisit",
           "map_offset", "revisit_error", "visit_maps"]

TOLERANCE = 1.0  # metres: revisit error and map offset at or under it close the loop


class Revisit(NamedTuple):
    """Frames i < j where the true path returns: ``gap_m`` = |p_j - p_i|, ``loop_m`` the true
    distance travelled from i to j."""

    i: int
    j: int
    gap_m: float
    loop_m: float


class Closure(NamedTuple):
    """The verdict at one revisit: ``closed`` when both figures are at most the tolerance
    (``map_offset_m`` is NaN, and the loop not closed, where the two visits' maps share too
    few cells to be compared)."""

    error_m: float
    map_offset_m: float
    map_corr: float
    closed: bool


def find_revisit(true: np.ndarray, start_m: float, min_loop_m: float,
                 radius: float = 2.0) -> Revisit | None:
    """The revisit of the frame i at ``start_m`` metres of travel along ``true`` [N, 3]: the
    frame j, at least ``min_loop_m`` of travel later, nearest to p_i; None when none comes
    within ``radius``."""
    true = np.asarray(true, np.float64)
    arc = arc_length(true)
    i = int(np.searchsorted(arc, start_m))
    later = np.flatnonzero(arc >= arc[min(i, len(arc) - 1)] + min_loop_m)
    if i >= len(arc) or later.size == 0:
        return None
    gaps = np.hypot(*(true[later, :2] - true[i, :2]).T)
    k = int(np.argmin(gaps))
    if gaps[k] > radius:
        return None
    j = int(later[k])
    return Revisit(i, j, float(gaps[k]), float(arc[j] - arc[i]))


def _seen_from(poses: np.ndarray, i: int, j: int) -> np.ndarray:
    """Position of frame j in the frame of the pose at i."""
    x, y, th = poses[i]
    d = poses[j, :2] - np.array([x, y])
    c, s = math.cos(th), math.sin(th)
    return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])


def revisit_error(true: np.ndarray, est: np.ndarray, i: int, j: int) -> float:
    """The revisit error (m) of ``est`` against ``true`` (both [N, 3]) at frames i, j."""
    true, est = np.asarray(true, np.float64), np.asarray(est, np.float64)
    return float(np.hypot(*(_seen_from(est, i, j) - _seen_from(true, i, j))))


def visit_maps(run: Run, poses: np.ndarray, revisit: Revisit,
               window: float = 5.0) -> tuple[GridMap, GridMap]:
    """The local maps of the frames within ``window`` metres of travel (along ``run``'s ground
    truth) of i and of j, each fused at ``poses`` into a map on one common grid."""
    arc = arc_length(run.ground_truth)
    obs = np.asarray(run.obs_index)
    out = []
    for f in (revisit.i, revisit.j):
        near = np.abs(arc - arc[f]) <= window
        out.append(pose_map(run._replace(obs_index=np.where(near, obs, -1)), poses))
    return out[0], out[1]


def expected_std(k: np.ndarray, S: np.ndarray) -> np.ndarray:
    """``cells.expected_std`` (E[h^-1/2]) in NumPy: no JAX compilation for each map's shape."""
    k, S = np.asarray(k, np.float64), np.asarray(S, np.float64)
    safe = np.where(k > 1, k, 2.0)
    bayes = np.sqrt(0.5 * S) * np.exp(gammaln(0.5 * (safe - 1.0)) - gammaln(0.5 * safe))
    with np.errstate(invalid="ignore", divide="ignore"):
        plain = np.sqrt(S / np.where(k > 0, k, 1.0))
    return np.where(k > 1, bayes, np.where(k > 0, plain, np.nan))


def map_offset(first: GridMap, second: GridMap, max_shift: float = 3.0,
               min_cells: int = 200) -> tuple[float, float]:
    """(offset in m, correlation there): the shift of ``second`` over ``first`` (same grid)
    whose expected standard deviations correlate best (Pearson) over the cells both know;
    NaN, NaN when no shift leaves ``min_cells`` cells known to both.

    Every shift d on the cell grid within ``max_shift`` compares first[x] with second[x + d]
    (a second copy displaced by d matches at d); the sums behind the correlation at all
    shifts are masked cross-correlations, computed by FFT.
    """
    if first.k.shape != second.k.shape or first.origin != second.origin:
        raise ValueError("the two maps must share one grid")
    ka = first.k > 0
    rows, cols = np.flatnonzero(ka.any(1)), np.flatnonzero(ka.any(0))
    if rows.size == 0:
        return math.nan, math.nan
    s = round(max_shift / first.resolution)
    r, c = slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1)
    ma = ka[r, c].astype(np.float64)
    a = np.where(ma > 0, expected_std(first.k[r, c], first.S[r, c]), 0.0)
    # the second map over the same cells and s more on each side (zero off the grid)
    pad = ((s, s), (s, s))
    r2, c2 = slice(rows[0], rows[-1] + 2 * s + 1), slice(cols[0], cols[-1] + 2 * s + 1)
    kb2, sb2 = np.pad(second.k, pad)[r2, c2], np.pad(second.S, pad)[r2, c2]
    mb = (kb2 > 0).astype(np.float64)
    b = np.where(mb > 0, expected_std(kb2, sb2), 0.0)

    def xcorr(u: np.ndarray, v: np.ndarray) -> np.ndarray:  # [2s+1, 2s+1]: sum_x u(x) v(x+d)
        return correlate(v, u, mode="valid", method="fft")

    n = np.rint(xcorr(ma, mb))
    sa, sb = xcorr(a, mb), xcorr(ma, b)
    saa, sbb, sab = xcorr(a * a, mb), xcorr(ma, b * b), xcorr(a, b)
    with np.errstate(invalid="ignore", divide="ignore"):
        cov = sab - sa * sb / n
        var = (saa - sa * sa / n) * (sbb - sb * sb / n)
        corr = np.where((n >= min_cells) & (var > 0), cov / np.sqrt(var), -np.inf)
    if not np.isfinite(corr).any():
        return math.nan, math.nan
    di, dj = np.unravel_index(int(np.argmax(corr)), corr.shape)
    return math.hypot(di - s, dj - s) * first.resolution, float(corr[di, dj])


def closure(run: Run, est: np.ndarray, revisit: Revisit, tolerance: float = TOLERANCE,
            window: float = 5.0, max_shift: float = 3.0) -> Closure:
    """The verdict for ``est`` [T, 3] (one pose per frame of ``run``) at ``revisit``, scored
    against ``run.ground_truth`` (see the module docstring)."""
    err = revisit_error(run.ground_truth, est, revisit.i, revisit.j)
    offset, corr = map_offset(*visit_maps(run, est, revisit, window), max_shift=max_shift)
    closed = bool(err <= tolerance and offset <= tolerance)  # NaN offset: not closed
    return Closure(err, offset, corr, closed)
