"""The pose an alignment reports and its covariance (``gridmap.align``).

At A's own lattice a quadratic fitted to the score around the best pose (the Laplace
approximation, as the observation-informed proposal fits its Gaussian: ``rbpf.proposal``) gives
the pose and the covariance of the tempered score: large where the score is flat (a straight
road's along-track direction). Two terms count what that curvature cannot, a score summed over
cells as if independent: the delete-one-block jackknife (``block_jackknife``: the fit repeated
with each of 8 contiguous stretches of B's map left out; neighbouring cells err together, and a
map bent by its own run's drift places differently stretch by stretch), and the disagreement of
the forward and the reverse search (``mutual_covariance``: a score rugged at the scale of a
cell, whose sharp local peak neither of the others widens).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from gslam_jax.gridmap.grid import invert_pose
from gslam_jax.gridmap.score import Level, MovingMap, score_pose_batch
from gslam_jax.rbpf.proposal import candidate_grid, quadratic_design, quadratic_hessian

__all__ = ["FLAT_VARIANCE", "PosePrior", "log_prior", "laplace_fit", "centroid", "map_blocks",
           "block_jackknife", "mutual_covariance"]


# variance, in squared grid steps, of a direction along which the score does not curve down
FLAT_VARIANCE = 1e12


class PosePrior(NamedTuple):
    """A Gaussian prior on B's pose in A's frame (e.g. from both runs' GPS alignments): mean
    [3], covariance [3, 3]. It restricts the global search to 4 standard deviations and adds
    its log density to the score."""

    mean: np.ndarray
    cov: np.ndarray


def log_prior(poses: np.ndarray, prior: PosePrior) -> np.ndarray:
    """Log density [N] of ``prior`` at ``poses`` [N, 3], up to a constant (heading wrapped)."""
    d = poses - prior.mean
    d[:, 2] = np.remainder(d[:, 2] + math.pi, 2 * math.pi) - math.pi
    return -0.5 * np.einsum("na,ab,nb->n", d, np.linalg.inv(prior.cov), d)


def laplace_fit(moving: MovingMap, lvl: Level, pose: np.ndarray, step: np.ndarray,
                prior: PosePrior | None, centre: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """Mode and covariance of the quadratic fitted to the score on a 5 x 5 x 5 grid of
    ``step`` around ``pose``, in the coordinates (``centre``, by default the centroid of B's
    cells, placed in A's frame; heading): turning about B's frame origin far from its cells
    would couple heading and shift into a narrow diagonal ridge that a quadratic on a grid fits
    badly. The mode stays within the grid; a direction where the fitted score does not curve
    down gets the variance ``FLAT_VARIANCE`` (in grid steps^2). The covariance is carried back
    to the pose."""
    c_b = centroid(moving) if centre is None else centre

    def to_pose(u: np.ndarray) -> np.ndarray:
        c, s = np.cos(u[..., 2]), np.sin(u[..., 2])
        return np.stack([u[..., 0] - (c * c_b[0] - s * c_b[1]),
                         u[..., 1] - (s * c_b[0] + c * c_b[1]), u[..., 2]], -1)

    c0, s0 = math.cos(pose[2]), math.sin(pose[2])
    u0 = np.array([pose[0] + c0 * c_b[0] - s0 * c_b[1], pose[1] + s0 * c_b[0] + c0 * c_b[1],
                   pose[2]])
    t, _ = candidate_grid(5, 2.0)
    t = np.asarray(t, np.float64)
    poses = to_pose(u0 + t * step)
    s = np.asarray(score_pose_batch(moving, jnp.asarray(poses, jnp.float32), lvl)[0], np.float64)
    if prior is not None:
        s = s + log_prior(poses, prior)
    coef = np.asarray(quadratic_design(jnp.asarray(t, jnp.float32)), np.float64) @ (s - s.max())
    b, H = quadratic_hessian(coef[None])
    b, H = np.asarray(b[0], np.float64), np.asarray(H[0], np.float64)
    vals, vecs = np.linalg.eigh(-H)
    curved = vals > 1e-9
    inv_vals = np.where(curved, 1.0 / np.where(curved, vals, 1.0), FLAT_VARIANCE)
    mode = np.clip(vecs @ (np.where(curved, inv_vals, 0.0) * (vecs.T @ b)), -2.0, 2.0)
    cov_u = ((vecs * inv_vals) @ vecs.T) * np.outer(step, step)
    u = u0 + mode * step
    c, s_ = math.cos(u[2]), math.sin(u[2])
    J = np.array([[1.0, 0.0, s_ * c_b[0] + c * c_b[1]],
                  [0.0, 1.0, -c * c_b[0] + s_ * c_b[1]],
                  [0.0, 0.0, 1.0]])
    return to_pose(u), J @ cov_u @ J.T


def centroid(moving: MovingMap) -> np.ndarray:
    """The mean [2] of B's known cells' centres, placed as ``moving`` holds them."""
    known = np.asarray(moving.k) > 0
    return np.asarray(moving.centres, np.float64)[known].mean(axis=0)


def map_blocks(centres: np.ndarray, along: int = 4, across: int = 2) -> np.ndarray:
    """Block index [N] of each of ``centres`` [N, 2]: ``along`` slabs of equal count along the
    cells' principal axis, each cut into ``across`` parts of equal count across it, so every
    block is one contiguous stretch of the map (of a path's map: a stretch of the drive)."""
    d = centres - centres.mean(axis=0)
    _, vecs = np.linalg.eigh(d.T @ d)
    u, v = d @ vecs[:, 1], d @ vecs[:, 0]  # principal axis first
    slab = np.minimum((np.argsort(np.argsort(u, kind="stable"), kind="stable") * along)
                      // len(u), along - 1)
    block = np.empty(len(u), np.int64)
    for a in range(along):
        sel = np.flatnonzero(slab == a)
        rank = np.argsort(np.argsort(v[sel], kind="stable"), kind="stable")
        block[sel] = a * across + np.minimum(rank * across // max(len(sel), 1), across - 1)
    return block


def block_jackknife(moving: MovingMap, lvl: Level, pose: np.ndarray, step: np.ndarray,
                    prior: PosePrior | None) -> np.ndarray:
    """Delete-one-block jackknife covariance [3, 3] of the fitted pose over ``map_blocks`` of
    B's cells: (n - 1) / n sum_i (T_i - T)(T_i - T)^T over the n fits without block i. It
    measures what the curvature of a score summed over cells as if independent cannot: cells
    that err together (neighbouring cells of one patch of terrain, a stretch of B's map bent by
    its own run's drift) move the pose together."""
    k = np.asarray(moving.k)
    known = np.flatnonzero(k > 0)
    block = np.full(len(k), -1)
    block[known] = map_blocks(np.asarray(moving.centres, np.float64)[known])
    centre = centroid(moving)
    fits = []
    for i in np.unique(block[known]):
        keep = jnp.asarray(block != i)
        held = moving._replace(k=jnp.where(keep, moving.k, 0.0), S=jnp.where(keep, moving.S, 0.0))
        fits.append(laplace_fit(held, lvl, pose, step, prior, centre)[0])
    fits = np.asarray(fits)
    d = fits - fits.mean(axis=0)
    d[:, 2] = np.remainder(fits[:, 2] - fits[0, 2] + math.pi, 2 * math.pi) - math.pi
    d[:, 2] -= d[:, 2].mean()
    n = len(fits)
    return (n - 1) / n * d.T @ d


def mutual_covariance(forward: np.ndarray, reverse: np.ndarray) -> np.ndarray:
    """The two searches' disagreement as a covariance [3, 3] of B's pose in A's frame:
    d d^T / 2, where d is the forward pose minus the inverse of the reverse one (A's frame in
    B's). Scoring B's cells on A's map and A's on B's are two estimates of one pose that weigh
    the maps' cells differently; if their errors were independent with covariance C, d would
    have covariance 2 C, so d d^T / 2 is a one-sample estimate of C. It counts what the
    curvature and the jackknife miss where the score is rugged at the scale of a cell: a
    quadratic fitted there reads a sharp peak, and every held-out fit stays on the same ridge
    (measured on the simulated maze: docs/notebook/results.md, "The reported uncertainty")."""
    back = invert_pose(np.asarray(reverse, np.float64))
    d = np.asarray(forward, np.float64) - back
    d[2] = math.remainder(d[2], 2 * math.pi)
    return 0.5 * np.outer(d, d)
