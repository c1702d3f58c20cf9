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
fitted to the score around the best pose gives the pose and its covariance, to which the
delete-one-block jackknife and, with the mutual check, the forward and the reverse search's
disagreement are added (``gridmap.pose_fit``).

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
from gslam_jax.gridmap.pose_fit import (FLAT_VARIANCE, PosePrior, block_jackknife, laplace_fit,
                                        log_prior, map_blocks, mutual_covariance)
from gslam_jax.gridmap.score import (Level, MovingMap, bucket, cell_terms, log_variance_range,
                                     moving_map, prepare, reach, reference_level,
                                     score_pose_batch)
from gslam_jax.rbpf.proposal import candidate_grid

__all__ = ["AlignParams", "PosePrior", "Alignment", "AlignmentRefused", "align_maps",
           "check_alignment", "map_blocks", "mutual_covariance", "FLAT_VARIANCE"]


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
        flat = flat + log_prior(poses, prior)
    return _distinct_peaks(poses, flat, params)


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
            s = s + log_prior(poses, prior)
        n = int(np.argmax(s))
        pose, best_score = poses[n], float(s[n])
        if np.all(np.abs(t[n]) < 2):
            break
    return pose, best_score


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
    best_pose, cov = laplace_fit(moving, lvl, refined[0][1], step, prior)
    if params.jackknife:
        cov = cov + block_jackknife(moving, lvl, best_pose, step, prior)
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
