"""Inlier detection by the rigidity constraint (Hirschmuller, Innocent & Garibaldi 2002;
Howard 2008 sec. 3.3; paper section 4 step 3).

Two matches i, j are consistent when the 3-D distance between their points is the same in both
frames (a rigid scene keeps distances). The consistency graph is built in one vectorised NumPy
expression, and the greedy maximum clique of Howard 2008 is grown with incremental degree updates,
so the whole step costs O(N^2) array work instead of O(N^2) Python iterations.
"""

from __future__ import annotations

import numpy as np

__all__ = ["consistency_graph", "greedy_max_clique", "rigid_inliers"]


def _pairwise_distances(p: np.ndarray) -> np.ndarray:
    """[N, N] Euclidean distances through the Gram matrix (|a|^2 + |b|^2 - 2 a.b): several
    times faster than norming an [N, N, 3] difference array; float64 keeps it exact to ~1e-7 m
    at the 100 m scale of stereo points. The Gram matrix is an einsum, not ``p @ p.T``: a
    threaded BLAS call on a 3-column product only adds overhead, and when other processes load
    the cores it made the 500-match graph 3-6x slower (8-16 ms instead of 2.5)."""
    p = p - p.mean(axis=0)  # centring keeps the cancellation small
    sq = np.einsum("ij,ij->i", p, p)
    d2 = sq[:, None] + sq[None, :] - 2.0 * np.einsum("ik,jk->ij", p, p)
    return np.sqrt(np.maximum(d2, 0.0))


def consistency_graph(points_a: np.ndarray, points_b: np.ndarray, threshold: float | np.ndarray
                      ) -> np.ndarray:
    """[N, N] bool: |‖a_i - a_j‖ - ‖b_i - b_j‖| < threshold (diagonal False).

    ``threshold`` may be a scalar (metres) or an [N] per-match tolerance; pairs use the sum of the
    two tolerances, so a far (noisy) point is judged leniently (stereo depth error grows as z^2).
    """
    da = _pairwise_distances(np.asarray(points_a, dtype=np.float64))
    db = _pairwise_distances(np.asarray(points_b, dtype=np.float64))
    thr = np.asarray(threshold, dtype=np.float64)
    if thr.ndim == 1:
        thr = thr[:, None] + thr[None, :]
    w = np.abs(da - db) < thr
    np.fill_diagonal(w, False)
    return w


def greedy_max_clique(w: np.ndarray) -> np.ndarray:
    """Indices of a large clique of the symmetric boolean graph ``w`` (Howard 2008, sec. 3.3).

    Start from the node of highest degree; repeatedly add the candidate (a node joined to every
    clique member) with most links to the other candidates. Deterministic: ties go to the lower
    index. Each node leaves the candidate set once, so the degree updates total O(N^2).
    """
    n = w.shape[0]
    if n == 0:
        return np.zeros(0, np.int64)
    wi = w.astype(np.int32)
    cand = np.ones(n, bool)
    deg = wi.sum(axis=1)  # links to current candidates
    clique = []
    while cand.any():
        v = int(np.argmax(np.where(cand, deg, -1)))
        clique.append(v)
        removed = cand & ~w[v]  # includes v itself (no self loops)
        cand &= w[v]
        if removed.any():
            deg -= wi[:, removed].sum(axis=1)
    return np.array(sorted(clique), np.int64)


def rigid_inliers(points_a: np.ndarray, points_b: np.ndarray, threshold: float | np.ndarray
                  ) -> np.ndarray:
    """Indices of the matches in the largest self-consistent (rigid) set."""
    return greedy_max_clique(consistency_graph(points_a, points_b, threshold))
