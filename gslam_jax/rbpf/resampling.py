"""Effective sample size (eq. 23) and resampling schemes.

Each scheme maps normalised weights w [J] and a vector of uniforms u [J] in [0, 1) to ancestor
indices [J]. Taking the uniforms as an argument (``draw_uniforms`` makes them) lets another
implementation, the tiled reference, be driven with the very same random numbers.
Multinomial is the paper's scheme; systematic, stratified and residual have lower variance.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
from jax import Array

__all__ = ["ess", "multinomial", "systematic", "stratified", "residual", "RESAMPLERS",
           "draw_uniforms", "resample", "keep_in_place"]


def ess(log_w: Array) -> Array:
    """Effective number of particles 1 / sum w^2 from normalised log weights (eq. 23)."""
    return 1.0 / jnp.sum(jnp.exp(2.0 * log_w))


# An ESS within this fraction above the resampling threshold counts as at it (resampled).
# Adaptive tempering puts the ESS exactly at ess_target * J, the threshold by default; float32
# sums in another order (particle blocks, another backend) must not flip the decision there.
THRESHOLD_TIE = 1e-3


def below_threshold(log_w: Array, ratio: float) -> Array:
    """Whether to resample (eq. 23): ESS < ratio * J, or within ``THRESHOLD_TIE`` above it."""
    return ess(log_w) < ratio * log_w.shape[0] * (1.0 + THRESHOLD_TIE)


def _inverse_cdf(w: Array, positions: Array) -> Array:
    cdf = jnp.cumsum(w)
    cdf = cdf / cdf[-1]
    idx = jnp.searchsorted(cdf, positions, side="right")
    return jnp.clip(idx, 0, w.shape[0] - 1).astype(jnp.int32)


def multinomial(w: Array, u: Array) -> Array:
    """J independent draws from Categorical(w) by inverse CDF."""
    return _inverse_cdf(w, u)


def systematic(w: Array, u: Array) -> Array:
    """One uniform shared by J evenly spaced positions (j + u_0) / J."""
    J = w.shape[0]
    return _inverse_cdf(w, (jnp.arange(J, dtype=w.dtype) + u[0]) / J)


def stratified(w: Array, u: Array) -> Array:
    """One uniform per stratum: positions (j + u_j) / J."""
    J = w.shape[0]
    return _inverse_cdf(w, (jnp.arange(J, dtype=w.dtype) + u) / J)


def residual(w: Array, u: Array) -> Array:
    """floor(J w_j) deterministic copies, the rest multinomial on the fractional parts.

    The residual weights are J w_j - floor(J w_j) (not w_j - floor(J w_j), a known bug in some
    libraries), renormalised; slot i >= sum floor(J w) takes residual draw u_i.
    """
    J = w.shape[0]
    Jw = J * w
    copies = jnp.floor(Jw)
    frac = Jw - copies
    n_det = jnp.sum(copies).astype(jnp.int32)
    slots = jnp.arange(J)
    det = jnp.searchsorted(jnp.cumsum(copies), slots, side="right").astype(jnp.int32)
    safe_frac = jnp.where(jnp.sum(frac) > 0, frac, jnp.ones_like(frac))
    rest = _inverse_cdf(safe_frac, u)
    return jnp.where(slots < n_det, jnp.clip(det, 0, J - 1), rest)


RESAMPLERS: dict[str, Callable[[Array, Array], Array]] = {
    "multinomial": multinomial,
    "systematic": systematic,
    "stratified": stratified,
    "residual": residual,
}


def draw_uniforms(key: Array, num_particles: int) -> Array:
    """The J uniforms every scheme consumes (systematic uses only the first)."""
    return jax.random.uniform(key, (num_particles,))


def resample(scheme: str, w: Array, u: Array) -> Array:
    """Ancestor indices by the named scheme; raises ValueError listing the valid names."""
    try:
        fn = RESAMPLERS[scheme]
    except KeyError:
        raise ValueError(f"unknown resampler '{scheme}'; choose one of {sorted(RESAMPLERS)}") from None
    return fn(w, u)


def keep_in_place(ancestors: Array) -> Array:
    """The same multiset of ancestors, arranged so that every surviving particle keeps its slot.

    Slot i gets ancestor i when particle i has offspring; the slots of particles without
    offspring, in increasing order, get the extra copies, parents in increasing order. Maps then
    only move into slots whose particle died, from slots that keep theirs, so resampling can
    copy them in place (``densestore.gather_particles``). Particle order carries no meaning in the
    filter, so this changes nothing but the cost.
    """
    J = ancestors.shape[0]
    counts = jnp.bincount(ancestors, length=J)
    extras = jnp.repeat(jnp.arange(J, dtype=jnp.int32), jnp.maximum(counts - 1, 0),
                        total_repeat_length=J)
    dead = counts == 0
    rank = jnp.cumsum(dead) - 1  # position of each dead slot among the dead slots
    return jnp.where(dead, extras[jnp.clip(rank, 0, J - 1)], jnp.arange(J)).astype(jnp.int32)
