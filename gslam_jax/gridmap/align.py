"""Global alignment of two variance grid maps by the gamma likelihood the filter weighs with.

The pose T = (x, y, theta) of map B's frame in map A's frame is the one that maximises the
score of ``gridmap.score``: B's cells placed by T on A's lattice, each scored against A's cell
by the log posterior predictive of eq. 26 as a log-likelihood ratio against chance, both maps
tempered to at most ``max_dof`` degrees of freedom per cell.

The search is global and coarse to fine. At level f the lattice has cells f x f times A's (the
statistics of eq. 14 summed per block, so a coarse cell holds the pooled within-cell variance of
its fine cells). The coarsest level scores every heading (steps that move B's farthest cell by
half a coarse cell) and every whole-cell shift, with B binned once per heading; its best
distinct peaks are refined level by level on local grids, and at A's own lattice a quadratic
fitted to the score around the best pose (the Laplace approximation, as the observation-informed
proposal fits its Gaussian: ``rbpf.proposal``) gives the pose and its covariance. The
covariance is that of the tempered score: large where the score is flat (a straight road's
along-track direction); to it is added the delete-one-block jackknife's (the fit repeated with
each of 8 contiguous stretches of B's map left out), which counts what the curvature cannot:
neighbouring cells err together, and a map bent by its own run's drift places differently
stretch by stretch; and, with the mutual check, half the outer product of the forward and the
reverse search's disagreement (``mutual_covariance``), which counts a score rugged at the scale
of a cell, whose sharp local peak neither of the others widens.

Decisions use a standardised score: z = score / sqrt(sum of the terms' variances under chance).
An alignment is refused (``AlignmentRefused``, carrying the best and the runner-up) when B
overlaps A too little, when z is too small to be told from chance, when a distinct runner-up
scores nearly as well (ambiguous) or when the score is flat in some direction.
"""

from __future__ import annotations

import math
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array, lax

from gslam_jax.errors import InputError
from gslam_jax.gridmap.grid import GridMap, compose, invert_pose
from gslam_jax.gridmap.score import (Level, MovingMap, bucket, cell_terms, log_variance_range,
                                     moving_map, prepare, reach, reference_level,
                                     score_pose_batch)
from gslam_jax.rbpf.proposal import candidate_grid, quadratic_design, quadratic_hessian

__all__ = ["AlignParams", "PosePrior", "Alignment", "AlignmentRefused", "align_maps",
           "check_alignment", "map_blocks", "mutual_covariance", "FLAT_VARIANCE"]


# variance, in squared grid steps, of a direction along which the score does not curve down
FLAT_VARIANCE = 1e12


class AlignParams(NamedTuple):
    """Settings of ``align_maps``.

    max_dof: degrees of freedom a cell counts for at most (tempering, see the module).
    coarse: cell factor of the coarsest level (a power of two); 0 chooses the smallest whose
        exhaustive search stays within ``budget`` cell evaluations.
    candidates: distinct coarse peaks refined to the fine lattice.
    min_overlap: fewest fine cells of B that must land on A's known cells.
    min_z: smallest standardised score accepted (chance gives about 0, with spread 1 per
        placement before the search's maximum over many placements).
    min_gap_z: how much better in z the best must be than the best distinct runner-up.
    distinct_m, distinct_rad: a runner-up is distinct when at least this far from the best in
        position or heading.
    max_std_m, max_std_rad: the largest standard deviation of the fitted pose accepted (a flat
        score along some direction is refused).
    budget: cell evaluations the coarsest level's exhaustive search may cost.
    mutual: also align A onto B; the two placements must agree (composed, within
        ``max_cycle_m`` and ``max_cycle_rad``). A map broken by its own run (walls doubled by a
        diverged filter) can score best at a wrong placement in a repetitive scene; the reverse
        search then finds another, and the merge is refused instead of made wrong. Their
        disagreement is also added to the covariance (``mutual_covariance``).
    jackknife: add the delete-one-block jackknife covariance (``map_blocks``) to the
        curvature's: the reported uncertainty then counts cells that err together.
    """

    max_dof: int = 8
    coarse: int = 0
    candidates: int = 8
    min_overlap: int = 200
    min_z: float = 12.0
    min_gap_z: float = 4.0
    distinct_m: float = 1.0
    distinct_rad: float = math.radians(10.0)
    max_std_m: float = 0.5
    max_std_rad: float = math.radians(2.0)
    budget: float = 4e8
    mutual: bool = True
    max_cycle_m: float = 0.5
    max_cycle_rad: float = math.radians(2.0)
    jackknife: bool = True


class PosePrior(NamedTuple):
    """A Gaussian prior on B's pose in A's frame (e.g. from both runs' GPS alignments): mean
    [3], covariance [3, 3]. It restricts the global search to 4 standard deviations and adds
    its log density to the score."""

    mean: np.ndarray
    cov: np.ndarray


class Alignment(NamedTuple):
    """B's frame in A's frame: pose [3] (x, y, theta) and its covariance [3, 3]; the score
    (sum of log-likelihood ratios, see the module) and its z; the fine cells of B that landed
    on A's known cells; the best distinct runner-up (pose, score, z; NaN when none); the
    coarse level used; how far the reverse alignment (A onto B), composed with this one, is
    from the identity (NaN when not checked)."""

    pose: np.ndarray
    covariance: np.ndarray
    score: float
    z: float
    overlap: int
    runner_up_pose: np.ndarray
    runner_up_score: float
    runner_up_z: float
    coarse: int
    cycle_m: float = math.nan
    cycle_rad: float = math.nan

    def summary(self) -> dict:
        std = np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
        return {"pose": [float(v) for v in self.pose],
                "heading_deg": math.degrees(float(self.pose[2])),
                "covariance": np.asarray(self.covariance).tolist(),
                "std_m": [float(std[0]), float(std[1])],
                "std_heading_deg": math.degrees(float(std[2])),
                "score": self.score, "z": self.z, "overlap_cells": self.overlap,
                "runner_up_pose": [float(v) for v in self.runner_up_pose],
                "runner_up_score": self.runner_up_score, "runner_up_z": self.runner_up_z,
                "coarse_level": self.coarse, "cycle_error_m": self.cycle_m,
                "cycle_error_deg": math.degrees(self.cycle_rad)}


class AlignmentRefused(InputError):
    """The maps do not overlap, or their match is too weak or ambiguous to trust; ``alignment``
    holds the best and runner-up found."""

    def __init__(self, message: str, alignment: Alignment):
        super().__init__(message)
        self.alignment = alignment


def _heading_step(radius: float, cell: float) -> float:
    """Heading step that moves B's farthest cell by half a cell of side ``cell``."""
    return min(0.5 * cell / max(radius, cell), math.radians(10.0))


@partial(jax.jit, static_argnames=("nx", "ny"))
def _shift_scores(bi: Array, bj: Array, bk: Array, bS: Array, lvl: Level, nx: int, ny: int
                  ) -> Array:
    """Scores [headings, nx, ny] of B's cells (k, S [N]) at padded lattice cells (bi, bj)
    [headings, N], shifted by every whole cell (sx, sy)."""

    def heading(ij):
        i, j = ij

        def row(sx):
            jj = j[None, :] + jnp.arange(ny)[:, None]
            ii = jnp.broadcast_to(i[None, :] + sx, jj.shape)
            ka = lvl.k.at[ii, jj].get(mode="fill", fill_value=0.0)  # beyond: unknown
            Sa = lvl.S.at[ii, jj].get(mode="fill", fill_value=0.0)
            g, _ = cell_terms(jnp.broadcast_to(bk, jj.shape), jnp.broadcast_to(bS, jj.shape),
                              ka, Sa, lvl)
            return jnp.sum(g, axis=1)

        return lax.map(row, jnp.arange(nx))

    return lax.map(heading, (bi, bj))


def _coarse_search(a: GridMap, b: GridMap, factor: int, params: AlignParams,
                   prior: PosePrior | None) -> tuple[np.ndarray, np.ndarray]:
    """Every heading and whole-cell shift at level ``factor``: the poses [n, 3] and scores [n]
    of the best distinct peaks (at most ``params.candidates``)."""
    moving = moving_map(b, factor, params.max_dof)
    centres = np.asarray(moving.centres, np.float64)
    r = a.resolution * factor
    radius = reach(b)
    pad = 2 * int(math.ceil(radius / r)) + 2
    lvl = reference_level(a, factor, pad, params.max_dof, log_variance_range(a, b))
    step = _heading_step(radius, r)
    if prior is not None:
        spread = 4.0 * math.sqrt(prior.cov[2, 2])
        n = max(1, int(math.ceil(spread / step)))
        headings = prior.mean[2] + step * np.arange(-n, n + 1)
    else:
        headings = np.arange(0.0, 2 * math.pi, step)
    # B's cells rotated per heading and indexed on a lattice of cell r through B's frame
    # origin: a translation of the padded lattice's origin plus whole cells n keeps those
    # indices (floor(x + n) = floor(x) + n), so each heading is indexed once for all shifts.
    c, s = np.cos(headings)[:, None], np.sin(headings)[:, None]
    bi = np.floor((c * centres[:, 0] - s * centres[:, 1]) / r).astype(np.int32)
    bj = np.floor((s * centres[:, 0] + c * centres[:, 1]) / r).astype(np.int32)
    # Shift index (sx, sy) puts B's cell (i, j) on padded cell (i - i_min + sx, ...), in range
    # for every B cell; the padding (twice B's reach) leaves no overlapping placement out.
    Hp, Wp = lvl.k.shape
    i_min, j_min = int(bi.min()), int(bj.min())
    bi_s, bj_s = bi - i_min, bj - j_min
    nx, ny = Hp - int(bi_s.max()), Wp - int(bj_s.max())
    # shapes padded to buckets so that later alignments reuse the compiled search
    Hd = len(headings)
    rows = np.minimum(np.arange(bucket(Hd, 16)), Hd - 1)
    scores = np.asarray(_shift_scores(jnp.asarray(bi_s[rows]), jnp.asarray(bj_s[rows]),
                                      moving.k, moving.S, lvl, bucket(nx, 8), bucket(ny, 8)),
                        np.float64)[:Hd, :nx, :ny]
    # Shift index sx is n = sx - i_min whole cells: B's frame origin at lattice origin + n r.
    sx = np.arange(nx) - i_min
    sy = np.arange(ny) - j_min
    xs = lvl.origin[0] + sx * r
    ys = lvl.origin[1] + sy * r
    poses = np.stack(np.broadcast_arrays(headings[:, None, None], xs[None, :, None],
                                         ys[None, None, :]), -1)[..., [1, 2, 0]].reshape(-1, 3)
    flat = scores.reshape(-1)
    if prior is not None:
        flat = flat + _log_prior(poses, prior)
    return _distinct_peaks(poses, flat, params)


def _log_prior(poses: np.ndarray, prior: PosePrior) -> np.ndarray:
    d = poses - prior.mean
    d[:, 2] = np.remainder(d[:, 2] + math.pi, 2 * math.pi) - math.pi
    return -0.5 * np.einsum("na,ab,nb->n", d, np.linalg.inv(prior.cov), d)


def _distinct(p: np.ndarray, q: np.ndarray, params: AlignParams) -> bool:
    dh = abs(math.remainder(float(p[2] - q[2]), 2 * math.pi))
    return math.hypot(p[0] - q[0], p[1] - q[1]) >= params.distinct_m or dh >= params.distinct_rad


def _distinct_peaks(poses: np.ndarray, scores: np.ndarray, params: AlignParams
                    ) -> tuple[np.ndarray, np.ndarray]:
    order = np.argsort(-scores, kind="stable")[: 200 * params.candidates]
    kept: list[int] = []
    for n in order:
        if all(_distinct(poses[n], poses[m], params) for m in kept):
            kept.append(int(n))
            if len(kept) == params.candidates:
                break
    return poses[kept], scores[kept]


def _refine(moving: MovingMap, lvl: Level, pose: np.ndarray, step: np.ndarray,
            prior: PosePrior | None, rounds: int = 10) -> tuple[np.ndarray, float]:
    """Local grid search: a 5 x 5 x 5 grid of ``step`` around the pose, re-centred on its
    best point until that is inside (at most ``rounds`` times): a hill climb to the peak."""
    t, _ = candidate_grid(5, 2.0)
    t = np.asarray(t, np.float64)
    best_score = -np.inf
    for _ in range(rounds):
        poses = pose + t * step
        s = np.asarray(score_pose_batch(moving, jnp.asarray(poses, jnp.float32), lvl)[0],
                       np.float64)
        if prior is not None:
            s = s + _log_prior(poses, prior)
        n = int(np.argmax(s))
        pose, best_score = poses[n], float(s[n])
        if np.all(np.abs(t[n]) < 2):
            break
    return pose, best_score


def _laplace(moving: MovingMap, lvl: Level, pose: np.ndarray, step: np.ndarray,
             prior: PosePrior | None, centre: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
    """Mode and covariance of the quadratic fitted to the score on a 5 x 5 x 5 grid of
    ``step`` around ``pose``, in the coordinates (``centre``, by default the centroid of B's
    cells, placed in A's frame; heading): turning about B's frame origin far from its cells
    would couple heading and shift into a narrow diagonal ridge that a quadratic on a grid fits
    badly. The mode stays within the grid; a direction where the fitted score does not curve
    down gets the variance ``FLAT_VARIANCE`` (in grid steps^2). The covariance is carried back
    to the pose."""
    c_b = _centroid(moving) if centre is None else centre

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
        s = s + _log_prior(poses, prior)
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


def _centroid(moving: MovingMap) -> np.ndarray:
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


def _jackknife(moving: MovingMap, lvl: Level, pose: np.ndarray, step: np.ndarray,
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
    centre = _centroid(moving)
    fits = []
    for i in np.unique(block[known]):
        keep = jnp.asarray(block != i)
        held = moving._replace(k=jnp.where(keep, moving.k, 0.0), S=jnp.where(keep, moving.S, 0.0))
        fits.append(_laplace(held, lvl, pose, step, prior, centre)[0])
    fits = np.asarray(fits)
    d = fits - fits.mean(axis=0)
    d[:, 2] = np.remainder(fits[:, 2] - fits[0, 2] + math.pi, 2 * math.pi) - math.pi
    d[:, 2] -= d[:, 2].mean()
    n = len(fits)
    return (n - 1) / n * d.T @ d


def _choose_coarse(a: GridMap, b: GridMap, params: AlignParams, prior: PosePrior | None) -> int:
    """The finest power-of-two level whose exhaustive search costs at most ``budget`` cell
    evaluations (headings x shifts x B's coarse cells)."""
    if params.coarse:
        return params.coarse
    radius = reach(b)
    nb = int(b.known.sum())
    factor = 1
    while True:
        r = a.resolution * factor
        headings = 2 * math.pi / _heading_step(radius, r)
        if prior is not None:
            headings = min(headings, 8 * math.sqrt(prior.cov[2, 2]) /
                           _heading_step(radius, r) + 1)
        shifts = (a.shape[0] / factor + 2 * radius / r) * (a.shape[1] / factor + 2 * radius / r)
        cells_b = max(1.0, nb / factor ** 2)
        if headings * shifts * cells_b <= params.budget or factor >= 64:
            return factor
        factor *= 2


def align_maps(a: GridMap, b: GridMap, params: AlignParams = AlignParams(),
               prior: PosePrior | None = None, refuse: bool = True) -> Alignment:
    """The pose of B's frame in A's frame that best places B's map on A's (the module's
    score), with its covariance and the best distinct runner-up; with ``params.mutual`` A is
    aligned onto B as well (under the inverse prior's mean, its covariance taken as it is) and
    the disagreement of the two recorded. With ``refuse`` (default) an overlap too small, a
    match too weak, ambiguous or not mutual, or a flat score raises ``AlignmentRefused`` naming
    the figures; otherwise the alignment is returned as found.

    Maps whose lattices are turned in their frames (``GridMap.heading``) are aligned in their
    lattices' axes and the result carried into their frames."""
    if not (a.heading or b.heading):
        return _align_lattices(a, b, params, prior, refuse)
    ha, hb = np.array([0.0, 0.0, a.heading]), np.array([0.0, 0.0, b.heading])
    # B's frame in A's = Ha (+) (B's lattice in A's lattice) (+) Hb^-1: linear in the latter,
    # with the Jacobian J (the position turned by A's heading)
    J = np.eye(3)
    J[:2, :2] = [[math.cos(a.heading), -math.sin(a.heading)],
                 [math.sin(a.heading), math.cos(a.heading)]]

    def to_frames(pose: np.ndarray) -> np.ndarray:
        return pose if not np.isfinite(pose).all() else compose(compose(ha, pose),
                                                                invert_pose(hb))

    lattice_prior = None if prior is None else PosePrior(
        compose(compose(invert_pose(ha), np.asarray(prior.mean, np.float64)), hb),
        J.T @ np.asarray(prior.cov, np.float64) @ J)
    al = _align_lattices(a._replace(heading=0.0), b._replace(heading=0.0), params,
                         lattice_prior, refuse=False)
    al = al._replace(pose=to_frames(al.pose), covariance=J @ al.covariance @ J.T,
                     runner_up_pose=to_frames(al.runner_up_pose))
    if refuse:
        check_alignment(al, params)
    return al


def _align_lattices(a: GridMap, b: GridMap, params: AlignParams, prior: PosePrior | None,
                    refuse: bool) -> Alignment:
    """``align_maps`` of two maps on their frames' axes (heading 0)."""
    if not math.isclose(a.resolution, b.resolution, rel_tol=1e-6):
        raise InputError(f"the maps have different resolutions ({a.resolution} m and "
                         f"{b.resolution} m); align maps built with one [map] resolution")
    for name, g in (("A", a), ("B", b)):
        if not g.known.any():
            raise InputError(f"map {name} has no known cell")
    factor = _choose_coarse(a, b, params, prior)
    poses, _ = _coarse_search(a, b, factor, params, prior)
    radius = reach(b)
    levels = {}
    f = max(factor // 2, 1)  # a search already at A's lattice is still refined there
    while f >= 1:
        levels[f] = prepare(a, b, f, params.max_dof)
        f //= 2
    refined: list[tuple[float, np.ndarray]] = []
    for pose in poses:
        for f, (moving, lvl) in levels.items():
            r = a.resolution * f
            step = np.array([r / 2, r / 2, _heading_step(radius, r)])
            pose, score = _refine(moving, lvl, pose, step, prior)
        # candidates that climbed to the same peak count once
        if all(_distinct(pose, p, params) for _, p in refined):
            refined.append((score, pose))
    refined.sort(key=lambda sp: -sp[0])
    moving, lvl = levels[1] if 1 in levels else prepare(a, b, 1, params.max_dof)
    # the fit spans +-2 cells: the score is piecewise constant within a cell, so a narrower
    # grid would fit its steps rather than its shape
    step = np.array([a.resolution, a.resolution, 2 * _heading_step(radius, a.resolution)])
    best_pose, cov = _laplace(moving, lvl, refined[0][1], step, prior)
    if params.jackknife:
        cov = cov + _jackknife(moving, lvl, best_pose, step, prior)
    others = [p for _, p in refined[1:] if _distinct(p, best_pose, params)]
    test = np.vstack([best_pose[None]] + [p[None] for p in others])
    score, var, overlap = (np.asarray(v, np.float64) for v in
                           score_pose_batch(moving, jnp.asarray(test, jnp.float32), lvl))
    z = score / np.sqrt(np.maximum(var, 1e-12))
    runner = int(np.argmax(score[1:])) + 1 if len(others) else None
    nan3 = np.full(3, np.nan)
    best_pose[2] = math.remainder(best_pose[2], 2 * math.pi)
    result = Alignment(
        pose=best_pose, covariance=cov, score=float(score[0]), z=float(z[0]),
        overlap=int(overlap[0]),
        runner_up_pose=test[runner] if runner else nan3,
        runner_up_score=float(score[runner]) if runner else math.nan,
        runner_up_z=float(z[runner]) if runner else math.nan, coarse=factor)
    if refuse:
        check_alignment(result, params)
    if params.mutual:
        reverse_prior = None if prior is None else PosePrior(
            invert_pose(prior.mean), prior.cov)
        back = _align_lattices(b, a, params._replace(mutual=False), reverse_prior,
                               refuse=False)
        cycle = compose(result.pose, back.pose)
        result = result._replace(covariance=result.covariance + mutual_covariance(
                                     result.pose, back.pose),
                                 cycle_m=float(math.hypot(cycle[0], cycle[1])),
                                 cycle_rad=float(abs(cycle[2])))
        if refuse:
            check_alignment(result, params)
    return result


def mutual_covariance(forward: np.ndarray, reverse: np.ndarray) -> np.ndarray:
    """The two searches' disagreement as a covariance [3, 3] of B's pose in A's frame:
    d d^T / 2, where d is the forward pose minus the inverse of the reverse one (A's frame in
    B's). Scoring B's cells on A's map and A's on B's are two estimates of one pose that weigh
    the maps' cells differently; if their errors were independent with covariance C, d would
    have covariance 2 C, so d d^T / 2 is a one-sample estimate of C. It counts what the
    curvature and the jackknife miss where the score is rugged at the scale of a cell: a
    quadratic fitted there reads a sharp peak, and every held-out fit stays on the same ridge
    (the maze trials of docs/results.md, heading std 0.003 deg against 0.13-0.21 deg off)."""
    back = invert_pose(np.asarray(reverse, np.float64))
    d = np.asarray(forward, np.float64) - back
    d[2] = math.remainder(d[2], 2 * math.pi)
    return 0.5 * np.outer(d, d)


def check_alignment(al: Alignment, params: AlignParams = AlignParams()) -> None:
    """Raise ``AlignmentRefused`` when the alignment cannot be trusted (see AlignParams)."""
    std = np.sqrt(np.clip(np.diag(al.covariance), 0.0, None))
    figures = (f"best z {al.z:.1f} (score {al.score:.0f}, {al.overlap} cells overlapping), "
               f"runner-up z {al.runner_up_z:.1f}")
    if al.overlap < params.min_overlap:
        why = f"the maps overlap by {al.overlap} cells at best (fewer than {params.min_overlap})"
    elif not al.z >= params.min_z:
        why = f"the best match is not told from chance (z below {params.min_z:g})"
    elif math.isfinite(al.runner_up_z) and al.z - al.runner_up_z < params.min_gap_z:
        rp = al.runner_up_pose
        why = (f"the match is ambiguous: a distinct placement at ({rp[0]:.2f} m, {rp[1]:.2f} m, "
               f"{math.degrees(rp[2]):.1f} deg) scores within {params.min_gap_z:g} in z")
    elif not (al.cycle_m <= params.max_cycle_m and al.cycle_rad <= params.max_cycle_rad) \
            and math.isfinite(al.cycle_m):
        why = (f"the alignment is not mutual: aligning A onto B places it {al.cycle_m:.2f} m "
               f"and {math.degrees(al.cycle_rad):.1f} deg from the inverse (one of the maps may "
               "be inconsistent in itself)")
    elif not (np.all(std[:2] <= params.max_std_m) and std[2] <= params.max_std_rad):
        why = (f"the score is flat along some direction (std {std[0]:.2f} m, {std[1]:.2f} m, "
               f"{math.degrees(std[2]):.2f} deg)")
    else:
        return
    raise AlignmentRefused(f"cannot align the maps: {why}; {figures}", al)
