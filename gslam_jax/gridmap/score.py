"""The gamma likelihood of one variance grid map placed on another, against chance.

Map B's cells, carried by a pose T = (x, y, theta) of B's frame in A's frame onto A's lattice,
are scored against A's cells with the log posterior predictive of eq. 26. Each cell's term is a
log-likelihood ratio against chance:

    g(b, a) = lambda(b | a) - E_a'[lambda(b | a')],

the expectation over A's known cells a' (what the unknown-cell model of eq. 31 would borrow),
so a placement on unrelated terrain scores 0 on average and a cell of B over unknown A scores 0.
The score of T is the sum of g over B's cells; z divides it by the square root of the terms'
summed variance under chance. Both maps' statistics are tempered to at most ``max_dof`` degrees
of freedom per cell (k and S scaled together, the variance kept): finished maps hold cells of
thousands of points whose exact variances differ between runs by more than their nominal
precision (different VO noise, different blur), and the untempered likelihood would trust them
beyond that.

A level f scores on a lattice of f x f of A's cells (eq. 14 summed per block: ``pool``). Its
``Level`` holds A there, padded, with the chance tables of g; its ``MovingMap`` holds B's known
cells there. The search that uses this score is ``gridmap.align``; the map's check against
itself is ``consistency``.
"""

from __future__ import annotations

import math
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array, lax

from gslam_jax.gridmap.grid import GridMap, known_cells
from gslam_jax.rbpf import cells

__all__ = ["temper", "pool", "Level", "MovingMap", "reference_level", "moving_map",
           "chance_tables", "cell_terms", "score_pose", "score_pose_batch", "score_poses",
           "prepare", "reach", "log_variance_range", "bucket"]


def temper(k: np.ndarray, S: np.ndarray, max_dof: int) -> tuple[np.ndarray, np.ndarray]:
    """(k, S) with k at most ``max_dof`` and whole (the fast eq. 26 needs integer k), S scaled
    by the same factor: the variance S / k is kept. Unknown cells (k = 0) stay (0, 0)."""
    k = np.asarray(k, np.float64)
    S = np.asarray(S, np.float64)
    kt = np.where(k > 0, np.clip(np.round(np.minimum(k, max_dof)), 1, max_dof), 0.0)
    return kt, np.where(k > 0, S * kt / np.where(k > 0, k, 1.0), 0.0)


def pool(grid: GridMap, factor: int) -> GridMap:
    """``grid`` on the lattice of factor x factor blocks (same origin): eq. 14 summed per
    block, so a block holds the pooled within-cell variance of its cells."""
    if factor == 1:
        return grid
    H, W = grid.shape
    Hp, Wp = -(-H // factor) * factor, -(-W // factor) * factor
    k = np.zeros((Hp, Wp))
    S = np.zeros((Hp, Wp))
    k[:H, :W], S[:H, :W] = grid.k, grid.S
    shape = (Hp // factor, factor, Wp // factor, factor)
    return GridMap(k.reshape(shape).sum(axis=(1, 3)), S.reshape(shape).sum(axis=(1, 3)),
                   grid.origin, grid.resolution * factor)


class Level(NamedTuple):
    """A's tempered, pooled map at one level, padded by at least ``pad`` cells on every side,
    and the chance baseline of g: mean and variance of lambda(b | a') over A's known cells,
    tabulated over b's tempered k (1..max_dof) and log variance."""

    factor: int
    k: Array            # [H + 2 pad, W + 2 pad]
    S: Array
    origin: tuple[float, float]  # world x, y of padded cell (0, 0)
    resolution: float
    base_mean: Array    # [max_dof + 1, V]
    base_var: Array
    log_v_grid: Array   # [V]


def cell_terms(kb: Array, Sb: Array, ka: Array, Sa: Array, lvl: Level) -> tuple[Array, Array]:
    """(g, chance variance of g) per cell, both 0 where b or a is unknown."""
    both = (kb > 0) & (ka > 0)
    one = jnp.ones_like(kb)
    kb_, Sb_ = jnp.where(kb > 0, kb, one), jnp.where(kb > 0, Sb, one)
    lam = cells.log_predictive_integer(kb_, Sb_, jnp.where(both, ka, one),
                                       jnp.where(both, Sa, one))
    log_v = jnp.log(Sb_ / kb_)
    grid = lvl.log_v_grid
    pos = jnp.clip((log_v - grid[0]) / (grid[1] - grid[0]), 0.0, grid.shape[0] - 1.001)
    i0 = jnp.floor(pos).astype(jnp.int32)
    frac = pos - i0
    row = jnp.clip(kb_, 0, lvl.base_mean.shape[0] - 1).astype(jnp.int32)

    def interp(table):
        return table[row, i0] * (1 - frac) + table[row, i0 + 1] * frac

    return (jnp.where(both, lam - interp(lvl.base_mean), 0.0),
            jnp.where(both, interp(lvl.base_var), 0.0))


def reference_level(a: GridMap, factor: int, pad: int, max_dof: int,
                    log_v_range: tuple[float, float], samples: int = 2048, points: int = 128
                    ) -> Level:
    """A at level ``factor`` (tempered after pooling) with its chance tables."""
    pooled = pool(a, factor)
    k, S = temper(pooled.k, pooled.S, max_dof)
    ka, Sa = k[k > 0], S[k > 0]
    if ka.size > samples:  # an even spread of A's known cells, deterministic
        pick = np.linspace(0, ka.size - 1, samples).astype(np.int64)
        ka, Sa = ka[pick], Sa[pick]
    # fewer cells are padded to ``samples`` with weight 0: one compiled table for every map
    weight = np.zeros(samples, np.float32)
    weight[:ka.size] = 1.0
    ka, Sa = (np.pad(x, (0, samples - x.size), constant_values=1.0) for x in (ka, Sa))
    lo, hi = log_v_range
    grid = np.linspace(lo - 1.0, hi + 1.0, points)
    lam_mean, lam_var = chance_tables(jnp.asarray(grid, jnp.float32), jnp.asarray(ka, jnp.float32),
                                       jnp.asarray(Sa, jnp.float32), jnp.asarray(weight), max_dof)
    mean = np.zeros((max_dof + 1, points))
    var = np.zeros((max_dof + 1, points))
    mean[1:], var[1:] = np.asarray(lam_mean), np.asarray(lam_var)
    # padded by ``pad`` cells before, and after up to a shape bucket (jit reuse; fine, as the
    # coarse search's shifts, and so its cost, grow with the padded shape)
    H, W = k.shape
    after = (bucket(H + 2 * pad, 16) - H - pad, bucket(W + 2 * pad, 16) - W - pad)
    kp = np.pad(k, ((pad, after[0]), (pad, after[1])))
    Sp = np.pad(S, ((pad, after[0]), (pad, after[1])))
    r = pooled.resolution
    return Level(factor, jnp.asarray(kp, jnp.float32), jnp.asarray(Sp, jnp.float32),
                  (a.origin[0] - pad * r, a.origin[1] - pad * r), r,
                  jnp.asarray(mean, jnp.float32), jnp.asarray(var, jnp.float32),
                  jnp.asarray(grid, jnp.float32))


@partial(jax.jit, static_argnames=("max_dof",))
def chance_tables(log_v: Array, ka: Array, Sa: Array, weight: Array, max_dof: int
                   ) -> tuple[Array, Array]:
    """Mean and variance over A's cells (ka, Sa [n], each counted with its ``weight``, 0 for
    padding) of lambda(b | a) for b of tempered k = 1..max_dof and variance exp(log_v)
    ([max_dof, V] each)."""
    kb = jnp.arange(1, max_dof + 1, dtype=jnp.float32)[:, None, None]
    Sb = kb * jnp.exp(log_v)[None, :, None]
    shape = (max_dof, log_v.shape[0], ka.shape[0])
    lam = cells.log_predictive_integer(jnp.broadcast_to(kb, shape), jnp.broadcast_to(Sb, shape),
                                       jnp.broadcast_to(ka, shape), jnp.broadcast_to(Sa, shape))
    w = weight / jnp.sum(weight)
    mean = jnp.sum(lam * w, axis=2)
    return mean, jnp.sum((lam - mean[..., None]) ** 2 * w, axis=2)


class MovingMap(NamedTuple):
    """B at one level: the centres [N, 2] (B's frame) of its known cells on its own lattice
    of that level (eq. 14 summed per block, then tempered), with their k, S [N]."""

    centres: Array
    k: Array
    S: Array


def bucket(n: int, quantum: int) -> int:
    """n rounded up to a multiple of ``quantum``: padded shapes that later alignments share,
    so the jitted scorers compile once per bucket rather than once per map."""
    return max(quantum, -(-n // quantum) * quantum)


def moving_map(b: GridMap, factor: int, max_dof: int) -> MovingMap:
    pooled = pool(b, factor)
    centres, k, S = known_cells(pooled)
    kt, St = temper(k, S, max_dof)
    # the coarse search costs in proportion to n, padding included: a coarse level's few
    # hundred cells are padded to multiples of 128, a fine level's thousands to 1024
    n = bucket(len(k), 128 if len(k) <= 1024 else 1024)
    pad = ((0, n - len(k)),)
    return MovingMap(jnp.asarray(np.pad(centres, pad + ((0, 0),)), jnp.float32),
                   jnp.asarray(np.pad(kt, pad), jnp.float32),
                   jnp.asarray(np.pad(St, pad), jnp.float32))


def score_pose(moving: MovingMap, pose: Array, lvl: Level) -> tuple[Array, Array, Array]:
    """(score, chance variance, B cells on A's known cells) of one pose at a level: each of
    B's cells is scored against the cell of A's lattice its centre falls in."""
    H, W = lvl.k.shape
    c, s = jnp.cos(pose[2]), jnp.sin(pose[2])
    x = pose[0] + c * moving.centres[:, 0] - s * moving.centres[:, 1]
    y = pose[1] + s * moving.centres[:, 0] + c * moving.centres[:, 1]
    i = jnp.floor((x - lvl.origin[0]) / lvl.resolution).astype(jnp.int32)
    j = jnp.floor((y - lvl.origin[1]) / lvl.resolution).astype(jnp.int32)
    inside = (i >= 0) & (i < H) & (j >= 0) & (j < W)
    ka = jnp.where(inside, lvl.k[jnp.clip(i, 0, H - 1), jnp.clip(j, 0, W - 1)], 0.0)
    Sa = jnp.where(inside, lvl.S[jnp.clip(i, 0, H - 1), jnp.clip(j, 0, W - 1)], 0.0)
    g, var = cell_terms(moving.k, moving.S, ka, Sa, lvl)
    return jnp.sum(g), jnp.sum(var), jnp.sum((ka > 0) & (moving.k > 0))


@jax.jit
def score_pose_batch(moving: MovingMap, poses: Array, lvl: Level) -> tuple[Array, Array, Array]:
    return lax.map(lambda p: score_pose(moving, p, lvl), poses)


def score_poses(a: GridMap, b: GridMap, poses: np.ndarray, factor: int = 1,
                max_dof: int = 8, pad: int | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(score, z, overlap) [n] of B placed at each of ``poses`` [n, 3] in A's frame, at the
    lattice of ``factor`` x ``factor`` A cells (the module's score). A's lattice is padded by
    ``pad`` cells (default: B's reach from its frame origin); B's cells placed off A's padded
    lattice lie over unknown cells either way, so the padding changes only the compiled shape
    (a fixed ``pad`` and A's shape: one compilation for many calls)."""
    moving, lvl = prepare(a, b, factor, max_dof, pad)
    score, var, overlap = score_pose_batch(moving, jnp.asarray(poses, jnp.float32), lvl)
    score, var = np.asarray(score, np.float64), np.asarray(var, np.float64)
    return score, score / np.sqrt(np.maximum(var, 1e-12)), np.asarray(overlap)


def log_variance_range(*grids: GridMap) -> tuple[float, float]:
    lo, hi = np.inf, -np.inf
    for g in grids:
        v = g.S[g.known] / g.k[g.known]
        lo, hi = min(lo, float(np.log(v.min()))), max(hi, float(np.log(v.max())))
    return lo, hi


def reach(b: GridMap) -> float:
    centres, _, _ = known_cells(b)
    return float(np.max(np.hypot(centres[:, 0], centres[:, 1]))) + b.resolution


def prepare(a: GridMap, b: GridMap, factor: int, max_dof: int, pad: int | None = None
             ) -> tuple[MovingMap, Level]:
    moving = moving_map(b, factor, max_dof)
    if pad is None:
        pad = int(math.ceil(reach(b) / (a.resolution * factor))) + 2
    return moving, reference_level(a, factor, pad, max_dof, log_variance_range(a, b))
