"""The filter's random numbers, frame by frame: per-frame keys, the proposal's standard
normals (independent or antithetic pairs) and the uniforms of an update. Drawn here, apart from
the math that uses them, so that another implementation (the tiled reference) can be driven
with exactly the same draws."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array

from gslam_jax.rbpf import proposal, resampling
from gslam_jax.rbpf.types import FilterConfig, UpdateNoise

__all__ = ["standard_normals", "motion_noise", "update_noise", "frame_keys"]


def standard_normals(key: Array, shape: tuple[int, int], draws: str) -> Array:
    """Standard normals [J, d] for a proposal, one row per particle.

    "independent": every row its own draw. "antithetic": rows ``j`` and ``j + ceil(J/2)`` are
    ``z`` and ``-z`` (an odd J leaves row ``J // 2`` unpaired). Every row is still N(0, I), so
    each particle's proposal and importance weight are unchanged; but the particles' unweighted
    mean draw is zero, so where the map's weights are flat their mean heading stays on the VO's
    (eq. 3 is additive; their mean position to first order in the noise) instead of taking a
    Monte Carlo error of O(sigma / sqrt(J)) that a random walk accumulates (antithetic
    variates; Owen, Monte Carlo theory, methods and examples, 8.2).
    """
    J, d = shape
    if draws == "independent":
        return jax.random.normal(key, (J, d), jnp.float32)
    if draws != "antithetic":
        raise ValueError(f"proposal draws '{draws}' unknown: 'independent' or 'antithetic' "
                         "('auto' is resolved by the run's sensor before)")
    z = jax.random.normal(key, ((J + 1) // 2, d), jnp.float32)
    return jnp.concatenate([z, -z])[:J]


def motion_noise(key: Array, cfg: FilterConfig) -> Array:
    """Standard-normal motion draws [J, 3] for one frame (along-track, heading, cross-track).

    The cross-track column comes from its own key, so the first two are the same draws whether
    or not the motion model has cross-track noise (``MotionParams.alpha_cross``)."""
    J = cfg.num_particles
    return jnp.concatenate(
        [standard_normals(key, (J, 2), cfg.proposal_draws),
         standard_normals(jax.random.fold_in(key, 2), (J, 1), cfg.proposal_draws)], axis=1)


def update_noise(key: Array, cfg: FilterConfig) -> UpdateNoise:
    """Uniforms for one update (unknown-cell sampling, then resampling)."""
    k_unknown, k_resample = jax.random.split(key)
    n = cfg.unknown_samples if cfg.unknown_cells == "sample" else 0
    z = (standard_normals(jax.random.fold_in(key, 1), (cfg.num_particles, 3),
                          cfg.proposal_draws) if proposal.select(cfg).normals else None)
    return UpdateNoise(
        unknown_u=jax.random.uniform(k_unknown, (cfg.num_particles, n), jnp.float32),
        resample_u=resampling.draw_uniforms(k_resample, cfg.num_particles),
        proposal_z=z,
    )


def frame_keys(key: Array, num_frames: int) -> Array:
    """Per-frame keys: frame t always uses the same key, however the run is chunked."""
    return jax.random.split(key, num_frames)
