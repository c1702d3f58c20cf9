"""Cell statistics of the variance grid map (paper 5.2-5.5).

A cell is summarised by (k, S): k degrees of freedom and S = k v, the sum of squared deviations
of its point heights from their mean. Stored that way, the conjugate update (eq. 14) is an
addition, and the log posterior predictive (eqs. 18, 26) needs no division.

Host-side helpers (NumPy, float64) turn point statistics (n, sum z, sum z^2) into (k, S);
device-side functions (jax.numpy) are elementwise and broadcast over any shape.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.scipy.special import gammaln

__all__ = ["stats_from_points", "obs_from_stats", "refine_obs", "merge_stats", "conjugate_update",
           "log_predictive", "log_predictive_integer", "log_v_obs", "lgamma_half",
           "log_likelihood_given_precision", "expected_std", "LGAMMA_TABLE_SIZE"]


def stats_from_points(z: np.ndarray) -> np.ndarray:
    """Sufficient statistics (n, sum z, sum z^2) of one cell's heights (eq. 5)."""
    z = np.asarray(z, dtype=np.float64).ravel()
    return np.array([z.size, z.sum(), np.dot(z, z)])


def merge_stats(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pool the points behind two sets of (n, sum z, sum z^2): an addition."""
    return np.asarray(a, dtype=np.float64) + np.asarray(b, dtype=np.float64)


def obs_from_stats(stats: np.ndarray, min_variance: float = 1e-6, weight: float = 1.0,
                   min_points: int = 2) -> np.ndarray:
    """(n, sum z, sum z^2)[..., 3] -> observation (k, S)[..., 2], float64 (paper 5.2).

    k = n - 1 and S = sum (z - mean)^2 for cells with n >= ``min_points`` (at least 2); cells
    with fewer points carry no information and get (0, 0). S comes from the one-pass formula
    sum z^2 - (sum z)^2 / n in float64 (no shift: heights far from 0 lose digits to
    cancellation), clipped at 0 against rounding, then floored at ``k * min_variance`` so that a
    cell of identical heights still has finite log S. ``min_variance`` must be positive for that
    (default 1e-6 m^2, the paper config's ``[map] min_variance``); with 0 such a cell gets S = 0
    and NaN log weights. ``weight`` scales both k and S (the variance S / k is kept): the
    degrees of freedom a cell's heights count for, as a fraction of n - 1 (1: the paper's
    independent heights; below 1 discounts heights that are correlated within a cell).
    ``refine_obs`` is the device twin of the last three steps.
    """
    if min_points < 2:
        raise ValueError(f"min_points must be at least 2 (one height has no variance), "
                         f"got {min_points}")
    stats = np.asarray(stats, dtype=np.float64)
    n, sz, szz = stats[..., 0], stats[..., 1], stats[..., 2]
    informative = n >= max(2, math.ceil(min_points))
    safe_n = np.where(informative, n, 1.0)
    S = np.maximum(szz - sz * sz / safe_n, 0.0)
    k = np.where(informative, n - 1.0, 0.0)
    S = np.where(informative, np.maximum(S, k * min_variance), 0.0)
    return np.stack([weight * k, weight * S], axis=-1)


def refine_obs(raw: Array, min_variance: Array | float, weight: Array | float = 1.0,
               min_points: Array | float = 2.0) -> Array:
    """Device twin of ``obs_from_stats``'s floor, weight and point threshold, applied to raw
    observations ``obs_from_stats(stats, min_variance=0)`` [..., 2]: traced (searchable,
    differentiable in ``min_variance`` and ``weight``) versions of the same settings. A cell
    keeps its observation when n = k + 1 >= ``min_points`` (a real threshold: n >= ceil)."""
    k, S = raw[..., 0], raw[..., 1]
    keep = (k > 0) & (k + 1.0 >= min_points)
    S = jnp.maximum(S, k * min_variance)
    return jnp.stack([jnp.where(keep, weight * k, 0.0), jnp.where(keep, weight * S, 0.0)], -1)


def conjugate_update(k_prior: Array, S_prior: Array, k_obs: Array, S_obs: Array) -> tuple[Array, Array]:
    """Posterior cell statistics after an observation (eq. 14): k'' = k' + k, S'' = S' + S."""
    return k_prior + k_obs, S_prior + S_obs


def log_predictive(k_obs: Array, S_obs: Array, k_prior: Array, S_prior: Array) -> Array:
    """Log posterior predictive density of the observed sample variance v = S/k (eqs. 18, 26).

    log lambda = lgamma(k''/2) - lgamma(k/2) - lgamma(k'/2)
               + 1/2 [k log S + k' log S' - k'' log S''] - log v,
    a proper density in v for k, k' > 0 (tested against quadrature and Monte Carlo).
    """
    k2 = k_obs + k_prior
    S2 = S_obs + S_prior
    return (gammaln(0.5 * k2) - gammaln(0.5 * k_obs) - gammaln(0.5 * k_prior)
            + 0.5 * (k_obs * jnp.log(S_obs) + k_prior * jnp.log(S_prior) - k2 * jnp.log(S2))
            - jnp.log(S_obs / k_obs))


def log_likelihood_given_precision(v: Array, k: Array, h: Array) -> Array:
    """Log density of the sample variance v of k+1 points given precision h (eq. 9).

    v ~ Gamma(shape k/2, rate h k/2).
    """
    a = 0.5 * k
    rate = 0.5 * h * k
    return a * jnp.log(rate) - gammaln(a) + (a - 1.0) * jnp.log(v) - rate * v


@jax.jit
def expected_std(k: Array, S: Array) -> Array:
    """Posterior expected standard deviation of a cell's heights, E[h^-1/2] (for display).

    With h ~ Gamma(k/2, rate S/2): E[h^-1/2] = sqrt(S/2) Gamma((k-1)/2) / Gamma(k/2), finite for
    k > 1; cells with 0 < k <= 1 fall back to sqrt(S/k); unknown cells (k = 0) are NaN.
    Jitted: called on whole maps of many shapes by the figures and exports, one compilation per
    shape instead of one per operation.
    """
    k = jnp.asarray(k)
    S = jnp.asarray(S)
    safe_k = jnp.where(k > 1, k, 2.0)
    bayes = jnp.sqrt(0.5 * S) * jnp.exp(gammaln(0.5 * (safe_k - 1.0)) - gammaln(0.5 * safe_k))
    plain = jnp.sqrt(S / jnp.where(k > 0, k, 1.0))
    return jnp.where(k > 1, bayes, jnp.where(k > 0, plain, jnp.nan))


# lgamma(k/2) for integer-valued k: a table below LGAMMA_TABLE_SIZE, Stirling's series above
# (absolute error < 1e-9 there). Much cheaper than jax.scipy gammaln on CPU.
LGAMMA_TABLE_SIZE = 16384
_LGAMMA_HALF = np.array([0.0] + [math.lgamma(0.5 * i) for i in range(1, LGAMMA_TABLE_SIZE)])


def lgamma_half(k: Array) -> Array:
    """lgamma(k / 2) for integer-valued k >= 1 (float array); 0 at k = 0 (callers mask it)."""
    table = jnp.asarray(_LGAMMA_HALF, dtype=jnp.float32)
    idx = jnp.clip(k, 0, LGAMMA_TABLE_SIZE - 1).astype(jnp.int32)
    looked_up = table.at[idx].get(mode="promise_in_bounds")
    x = jnp.maximum(0.5 * k, 1.0)
    stirling = (x - 0.5) * jnp.log(x) - x + 0.5 * math.log(2 * math.pi) + 1.0 / (12.0 * x)
    return jnp.where(k < LGAMMA_TABLE_SIZE, looked_up, stirling)


def _log_ratios(S_obs: Array, S_prior: Array) -> tuple[Array, Array]:
    """(log r, log q) with r = S / S'' and q = S' / S'' = 1 - r, both to float32 rounding.

    Only the smaller ratio m = min(S, S') / S'' <= 1/2 is formed: the smaller log is log m and
    the larger is log1p(-m). (1 - r has no digits left when one variance dwarfs the other, e.g.
    a flat prior cell under a tall observation.) Two logs and one division per cell.
    """
    m = jnp.minimum(S_obs, S_prior) / (S_obs + S_prior)
    log_m, log_rest = jnp.log(m), jnp.log1p(-m)
    obs_smaller = S_obs <= S_prior
    return jnp.where(obs_smaller, log_m, log_rest), jnp.where(obs_smaller, log_rest, log_m)


# lgamma(k''/2) - lgamma(k_big/2) for k_big < 16: a table of the float32 differences of the
# float32 table values (both are small there, so the difference is exact to float32 rounding).
_SMALL = 16
_LGAMMA_HALF_F32 = _LGAMMA_HALF.astype(np.float32)
_LGAMMA_HALF_DIFF = np.zeros((_SMALL, _SMALL), np.float32)
for _b in range(_SMALL):
    for _s in range(_b + 1):
        _LGAMMA_HALF_DIFF[_b, _s] = _LGAMMA_HALF_F32[_b + _s] - _LGAMMA_HALF_F32[_b]


def log_v_obs(k_obs: Array, S_obs: Array) -> Array:
    """log v = log(S / k) of observed cells (0 where k = 0): the last term of eq. 26, which
    depends on the observation only and so can be computed once for all particles."""
    has = k_obs > 0
    return jnp.where(has, jnp.log(jnp.where(has, S_obs, 1.0)) - jnp.log(jnp.where(has, k_obs, 1.0)),
                     0.0)


def log_predictive_integer(k_obs: Array, S_obs: Array, k_prior: Array, S_prior: Array,
                           log_v: Array | None = None) -> Array:
    """``log_predictive`` (eq. 26) for integer-valued k, k' >= 1, arranged for float32.

    Eq. 26 is a small difference of large terms (k'' log S'' and lgamma(k''/2) reach 1e4 for
    well-observed cells). Rewritten with r = S / S'' and q = S' / S'' = 1 - r:
        lgamma(k''/2) - lgamma(k_big/2) - lgamma(k_small/2) + 1/2 [k log r + k' log q] - log v,
    with k_big, k_small the larger and smaller of k, k'. The lgamma difference is Stirling's
    series differenced term by term for k_big >= 16 ((x - 1/2) log1p(a/x) + a log(x + a) - a
    + ..., error < 1e-7) and a 16 x 16 table below; lgamma(k_small/2) is a table lookup
    (Stirling above ``LGAMMA_TABLE_SIZE``); log r, log q come from the smaller of the two ratios
    (``_log_ratios``). Two table lookups per cell, valid for every k (no branch for the caller).
    ``log_v`` = ``log_v_obs(k_obs, S_obs)`` may be passed in when many priors share it.
    """
    k_big = jnp.maximum(k_obs, k_prior)
    k_small = jnp.minimum(k_obs, k_prior)
    x = jnp.maximum(0.5 * k_big, 8.0)
    a = 0.5 * k_small
    y = x + a
    stirling = ((x - 0.5) * jnp.log1p(a / x) + a * jnp.log(y) - a
                + (1.0 / 12.0) * (1.0 / y - 1.0 / x) - (1.0 / 360.0) * (1.0 / y**3 - 1.0 / x**3))
    small = jnp.clip(k_big, 0, _SMALL - 1).astype(jnp.int32) * _SMALL \
        + jnp.clip(k_small, 0, _SMALL - 1).astype(jnp.int32)
    table = jnp.asarray(_LGAMMA_HALF_DIFF).reshape(-1).at[small].get(mode="promise_in_bounds")
    diff = jnp.where(k_big >= 16.0, stirling, table)
    log_r, log_q = _log_ratios(S_obs, S_prior)
    if log_v is None:
        log_v = jnp.log(S_obs) - jnp.log(k_obs)
    return diff - lgamma_half(k_small) + 0.5 * (k_obs * log_r + k_prior * log_q) - log_v
