"""The importance factor of each particle: the log-gamma posterior predictive of its observed
cells against its map (eq. 26), tempered and combined over the footprint (eq. 30, or eq. 31 with
unknown cells borrowing a random known cell)."""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jax import Array

from gslam_jax.rbpf import cells
from gslam_jax.rbpf.footprint import Footprint
from gslam_jax.rbpf.types import FilterConfig, FilterParams

__all__ = ["log_importance", "log_lambda", "cell_noise", "known_cell_terms"]


def log_importance(k_obs: Array, S_obs: Array, k_prior: Array, S_prior: Array,
                   k_borrow: Array, S_borrow: Array, can_borrow: Array,
                   params: FilterParams, unknown_cells: str, noise: Array | None = None
                   ) -> Array:
    """Tempered log importance factor of one particle, eqs. 26 and 30 / 31.

    All inputs are per-cell arrays of one footprint; (k_borrow, S_borrow) are the sampled known
    cells used for unknown cells in "sample" mode. Masked cells get harmless stand-ins so that
    neither the value nor the gradient sees a log(0).

    noise: per observed cell, the variance its measurement adds at its range (``cell_noise``):
    the map cell (k', S') then predicts the observed variance about S'/k' + noise, i.e. it
    enters eq. 26 as (k', S' + k' noise). A cell mapped from close by (tiny variance, many
    points) is otherwise all but impossible when seen again from afar, and a correct revisit
    scores below chance (docs/notebook/results.md, "How long a loop closes").
    """
    return _log_importance(k_obs, S_obs, k_prior, S_prior, k_borrow, S_borrow, can_borrow,
                           params, unknown_cells, noise=noise)


def cell_noise(obs_index: Array, params: FilterParams) -> Array | None:
    """The measurement variance of each observed local cell (flat indices ``obs_index`` [M])
    from ``params.range_noise``; None when the params carry none."""
    if params.range_noise is None:
        return None
    return jnp.take(jnp.asarray(params.range_noise), obs_index, mode="clip")


def known_cell_terms(k_obs: Array, S_obs: Array, k_prior: Array, S_prior: Array,
                     noise: Array | None = None, log_v: Array | None = None
                     ) -> tuple[Array, Array]:
    """Eq. 26 at each observed cell whose map cell is known (G_prev of eqs. 29-31), for
    per-cell arrays of any shape (e.g. [n, M] footprints): (known [..., M], log lambda_g
    [..., M], 0 where not known). ``noise`` and ``log_v`` as in ``log_importance``."""
    has = k_obs > 0
    prev = has & (k_prior > 0)
    one = jnp.ones_like(k_obs)
    if noise is not None:
        S_prior = S_prior + k_prior * noise
    lam = cells.log_predictive_integer(jnp.where(has, k_obs, one), jnp.where(has, S_obs, one),
                                       jnp.where(prev, k_prior, one),
                                       jnp.where(prev, S_prior, one), log_v=log_v)
    return prev, jnp.where(prev, lam, 0.0)


def _log_importance(k_obs, S_obs, k_prior, S_prior, k_borrow, S_borrow, can_borrow,
                    params, unknown_cells, log_v=None, noise=None):
    """``log_importance``; ``log_v`` (``cells.log_v_obs``) may be passed in when shared, and
    in "sample" mode k_borrow, S_borrow may be the draws themselves ([D], see below)."""
    log_pred = partial(cells.log_predictive_integer, log_v=log_v)
    has = k_obs > 0
    one = jnp.ones_like(k_obs)
    ko, So = jnp.where(has, k_obs, one), jnp.where(has, S_obs, one)
    prev, lam_prev = known_cell_terms(k_obs, S_obs, k_prior, S_prior, noise, log_v)
    sum_prev = jnp.sum(lam_prev)
    if unknown_cells == "ignore":  # eq. 30
        n_prev = jnp.sum(prev)
        return jnp.where(n_prev > 0, sum_prev / (params.beta_prev * jnp.maximum(n_prev, 1)), 0.0)
    if k_borrow.shape == k_obs.shape:
        new = has & ~prev & can_borrow & (k_borrow > 0)
        if noise is not None:
            S_borrow = S_borrow + k_borrow * noise
        lam_new = log_pred(ko, So, jnp.where(new, k_borrow, one), jnp.where(new, S_borrow, one))
    else:
        # k_borrow, S_borrow are the draws [D]; cell c borrows draw c mod D. Eq. 26 runs over
        # the cells laid out [rows, D] with the draws broadcast over the rows, which XLA CPU
        # runs faster than the draws tiled out to [M] (docs/notebook/results.md, "Moved
        # from code comments").
        D = k_borrow.shape[0]
        grid = partial(_by_draw, draws=D)
        log_v = cells.log_v_obs(k_obs, S_obs) if log_v is None else log_v
        kb = jnp.where(can_borrow & (k_borrow > 0), k_borrow, 0.0)[None, :]
        new = grid(has & ~prev) & (kb > 0)
        Sb = S_borrow[None, :] if noise is None else S_borrow[None, :] + kb * grid(noise)
        # padding: a cell with k = S = 1 (log v = 0), finite, never new (not in the sum below)
        # The sum runs on the grid: slicing [:M] back out of it first made XLA CPU run the
        # whole kernel 2-3x slower when M is not a multiple of D.
        lam_new = cells.log_predictive_integer(grid(ko, fill=1), grid(So, fill=1),
                                               jnp.where(new, kb, 1.0),
                                               jnp.where(new, Sb, 1.0),
                                               log_v=grid(log_v))
    sum_new = jnp.sum(jnp.where(new, lam_new, 0.0))
    n_obs = jnp.maximum(jnp.sum(has), 1)
    return (sum_prev / params.beta_prev + sum_new / params.beta_new) / n_obs  # eq. 31


def _by_draw(x: Array, draws: int, fill: float = 0) -> Array:
    """[M] per-cell values -> [ceil(M / draws), draws], padded with ``fill``: cell c sits in
    column c mod draws, the column of the draw it borrows."""
    rows = -(-x.shape[0] // draws)
    return jnp.pad(x, (0, rows * draws - x.shape[0]), constant_values=fill).reshape(rows, draws)


def log_lambda(f: Footprint, log_v: Array, params: FilterParams, cfg: FilterConfig,
               noise: Array | None = None) -> Array:
    """[n] log importance factors from the stacked reads (eq. 26 with eq. 30 / 31); log_v [M]
    (``cells.log_v_obs`` of the observed cells) and noise [M] (``cell_noise``, or None) are
    shared by every particle. In "sample" mode observed cell c borrows draw c mod
    unknown_samples."""

    def one(k_obs, S_obs, k_prior, S_prior, kb, Sb, can_borrow):
        if cfg.unknown_cells != "sample":
            kb, Sb = k_obs, S_obs
        elif kb.shape[0] >= k_obs.shape[0]:
            kb, Sb = kb[:k_obs.shape[0]], Sb[:k_obs.shape[0]]
        return _log_importance(k_obs, S_obs, k_prior, S_prior, kb, Sb, can_borrow, params,
                               cfg.unknown_cells, log_v, noise)

    return jax.vmap(one)(f.k_obs, f.S_obs, f.k_prior, f.S_prior, f.k_draws, f.S_draws,
                         f.can_borrow)
