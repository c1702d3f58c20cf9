"""Adaptive tempering of the importance weights, as in adaptive SMC.

The paper tempers each update's log importance factors by fixed independence factors beta
(eqs. 30-31: log lambda / beta). On real stereo those factors are far too peaked: neighbouring
cells share stereo errors, so the effective number of independent cells is much smaller than
1 / beta assumes, and the particle set collapses at every local map. Adaptive SMC (Jasra et al.
2011; Zhou, Johansen and Aston 2016) instead picks the exponent of each incremental weight so
that the particle set keeps a target effective sample size. Here the update's increments are
the paper's tempered ``log_lam`` times an exponent ``phi`` in [0, 1]: ``phi = 1`` (the paper's
fixed beta) wherever that keeps the conditional ESS at or above ``target * J``, else the
largest ``phi`` that does. Where the data are benign the paper's behaviour is kept exactly.

The conditional ESS (Zhou et al. 2016, eq. 3.5) of increments ``phi * log_lam`` under the
normalised weights W is ``(sum W e^{phi l})^2 / sum W e^{2 phi l}`` (J times a fraction in
(1/J, 1]); it equals the ESS after reweighting when W is uniform (after a resampling) and is
non-increasing in ``phi`` for any W, so bisection finds the exponent.

With the observation-informed proposal (``rbpf.proposal``) what an update leaves in particle
j's weight is not its factor at one pose but the normaliser of what it was drawn from,
Z_j(phi) = E_prior[e^{phi log lambda_j}]; ``normaliser_exponent`` keeps the conditional ESS of
those (estimated on the proposal's candidate grid) instead: a spread the proposal absorbs into
the draw does not flatten the score it fits.

``phi`` is held constant under differentiation (``lax.stop_gradient``): gradients flow through
``log_lam`` at the chosen exponent, as adaptive-SMC analyses treat the chosen temperatures.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
from jax import Array, lax

from gslam_jax import choices

__all__ = ["TEMPERING", "BISECTION_STEPS", "conditional_ess", "largest_exponent",
           "adaptive_exponent", "exponent", "grid_log_normaliser", "normaliser_exponent"]

TEMPERING = choices.TEMPERING
BISECTION_STEPS = 30  # interval 2^-30 on [0, 1]: below float32 resolution near 1


def conditional_ess(log_w: Array, log_lam: Array, phi: Array | float) -> Array:
    """Conditional ESS fraction in (0, 1] of increments ``phi * log_lam`` under the normalised
    log weights ``log_w`` (both [J]): ``(sum W e^{phi l})^2 / sum W e^{2 phi l}``."""
    x = phi * log_lam
    return jnp.exp(2.0 * jax.nn.logsumexp(log_w + x) - jax.nn.logsumexp(log_w + 2.0 * x))


def largest_exponent(ok: Callable[[Array], Array], steps: int = BISECTION_STEPS) -> Array:
    """1 if ``ok(1)``, else the bisection's lower end after ``steps`` halvings of [0, 1]: the
    largest exponent ``phi`` with ``ok(phi)`` when ``ok`` holds below some exponent and fails
    above it (within 2^-steps, never above it). Jit-friendly: fixed iterations, scalar state."""

    def bisect(_, lo_hi):
        lo, hi = lo_hi
        mid = 0.5 * (lo + hi)
        good = ok(mid)
        return jnp.where(good, mid, lo), jnp.where(good, hi, mid)

    one = jnp.ones((), jnp.float32)
    lo, _ = lax.fori_loop(0, steps, bisect, (jnp.zeros_like(one), one))
    return jnp.where(ok(one), one, lo)


def adaptive_exponent(log_w: Array, log_lam: Array, target: float,
                      steps: int = BISECTION_STEPS) -> Array:
    """The largest ``phi`` in [0, 1] whose conditional ESS fraction is at least ``target``
    (1 when ``phi = 1`` already meets it), by ``steps`` bisection steps; the result is within
    2^-steps below the exact exponent and never above 1. Jit-friendly (fixed iteration count,
    scalar state), its gradient is zero (see the module docstring).

    log_w: [J] normalised log weights before the update; log_lam: [J] the update's log
    importance factors at the paper's fixed beta (eq. 30 / 31); target in (0, 1].
    """
    log_w = lax.stop_gradient(log_w)
    log_lam = lax.stop_gradient(log_lam)
    # Particles with zero weight carry no mass: their factors must not move the exponent.
    log_lam = jnp.where(jnp.isfinite(log_w), log_lam, 0.0)
    phi = largest_exponent(
        lambda phi: conditional_ess(log_w, log_lam, phi) >= target, steps)
    return phi.astype(log_lam.dtype)



def exponent(log_w: Array, log_lam: Array, rule: str, target: float) -> Array:
    """An update's exponent of its log factors ``log_lam`` under the normalised log weights
    ``log_w``, by ``[filter] tempering`` ``rule``: 1 with "fixed" (the paper's beta as it is),
    ``adaptive_exponent`` with "adaptive"."""
    if rule == "adaptive":
        return adaptive_exponent(log_w, log_lam, target)
    return jnp.ones((), log_lam.dtype)

def grid_log_normaliser(log_lam: Array, log_prior: Array, phi: Array | float) -> Array:
    """log Z_j(phi) [J] = log of the prior-weighted mean of e^{phi log lambda_jk} over each
    particle's candidates k (``log_lam``, ``log_prior`` [J, K]: the factors and the log prior
    densities at a grid over the prior): the quadrature estimate of what a proposal fitted to
    the tempered target leaves in the weight, the target's normaliser against the prior's."""
    return (jax.nn.logsumexp(phi * log_lam + log_prior, axis=1)
            - jax.nn.logsumexp(log_prior, axis=1))


def normaliser_exponent(log_w: Array, log_lam: Array, log_prior: Array, target: float,
                        steps: int = BISECTION_STEPS) -> Array:
    """The largest ``phi`` in [0, 1] whose increments ``grid_log_normaliser(log_lam, log_prior,
    phi)`` keep the conditional ESS fraction under ``log_w`` [J] at least ``target`` (1 when
    ``phi = 1`` does), by bisection; ``log_lam``, ``log_prior`` [J, K] are each particle's
    candidates'. Zero gradient, as ``adaptive_exponent``'s."""
    log_w, log_lam, log_prior = map(lax.stop_gradient, (log_w, log_lam, log_prior))
    # a candidate with no finite factor counts as the particle's worst; a particle with zero
    # weight carries no mass and must not move the exponent
    floor = jnp.min(jnp.where(jnp.isfinite(log_lam), log_lam, jnp.inf), axis=1, keepdims=True)
    log_lam = jnp.where(jnp.isfinite(log_lam), log_lam, floor)
    log_lam = jnp.where(jnp.isfinite(log_w)[:, None], log_lam, 0.0)

    def ok(phi: Array) -> Array:
        inc = grid_log_normaliser(log_lam, log_prior, phi)
        return conditional_ess(log_w, inc, 1.0) >= target

    return largest_exponent(ok, steps).astype(log_lam.dtype)
