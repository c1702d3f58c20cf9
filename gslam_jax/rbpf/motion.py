"""Motion model (paper 5.1, eqs. 1-3).

x_t = x_{t-1} + Delta d_t + q_d,  theta_t = theta_{t-1} + Delta theta_t + q_theta, where
Delta d_t is the VO translation rotated into the world frame, q_d is Gaussian noise along
Delta d_t with std sigma_d = alpha_d |Delta d| and q_theta has std
sigma_theta = alpha_theta_d |Delta d| + alpha_theta |Delta theta|.

The paper's q_d has no component across Delta d_t. Stereo VO can err across the track about as
much as along it (docs/notebook/real-data.md, "Cross-track noise"), so q_d may also have a
cross-track part of std sigma_c = alpha_cross |Delta d|, independent of the others;
alpha_cross = 0 (the default) is the paper's model exactly.

Noise enters reparameterised (eps ~ N(0, 1) times sigma), so samples are differentiable in the
alphas.

A frame whose control came from the fallback odometry (wheels and IMU where VO failed; paper 4:
"less accurate than those from VO") takes every std times ``fallback_scale`` (``scaled``,
``[motion] fallback_scale``), a parameter like the alphas: searchable and differentiable.

With ``[motion] noise_spread`` s > 1 each particle carries its own factor on every std
(``particle_scales``: over (1/s, s), dense near 1); the factor is resampled with the particle, so
the filter weighs noise levels by the same evidence as poses (the static-parameter particle
filter; Kantas et al., On particle methods for parameter estimation in state-space models,
Statistical Science 2015, 3.1): where the alphas are wrong, the particles whose noise fits
the log survive.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

__all__ = ["MotionParams", "scaled", "particle_scales", "motion_stds", "world_step",
           "control_between", "apply_motion", "sample_motion", "log_density"]


class MotionParams(NamedTuple):
    """The VO error constants of eqs. 2-3, the cross-track one (0: the paper's model) and the
    fallback odometry's stds as a multiple of the VO's (1: the same; applied by the filter on
    the frames a Run flags ``vo_failed``). Defaults: ``config.MotionSection``."""

    alpha_d: Array | float
    alpha_theta_d: Array | float
    alpha_theta: Array | float
    alpha_cross: Array | float = 0.0
    fallback_scale: Array | float = 1.0


def scaled(params: MotionParams, scale: Array | float) -> MotionParams:
    """``params`` with every noise std (sigma_d, sigma_theta, sigma_c of eqs. 2-3) times
    ``scale``: the motion model of a frame whose control is ``scale`` times as uncertain
    (``fallback_scale`` is kept: it is a ratio, not a std)."""
    return params._replace(alpha_d=params.alpha_d * scale,
                           alpha_theta_d=params.alpha_theta_d * scale,
                           alpha_theta=params.alpha_theta * scale,
                           alpha_cross=params.alpha_cross * scale)


def particle_scales(num_particles: int, spread: float) -> Array:
    """Each particle's factor on the motion stds [J]: spread^(u^3) for u the midpoints of
    P = ceil(J / 2) equal steps of [-1, 1], so every factor lies in (1 / spread, spread) and
    half of them within spread^(+-1/8) of 1 (the alphas given; why not log-uniform:
    docs/notebook/results.md, "Motion noise: the particles' own"), rows j and j + P equal, so
    that an antithetic pair
    (``draws.standard_normals``) shares its noise."""
    P = (num_particles + 1) // 2
    u = (2.0 * jnp.arange(P) + 1.0) / P - 1.0
    levels = jnp.exp(math.log(spread) * u ** 3)
    return jnp.concatenate([levels, levels])[:num_particles].astype(jnp.float32)


def motion_stds(u: Array, params: MotionParams) -> tuple[Array, Array, Array]:
    """(|Delta d|, sigma_d, sigma_theta) for a control u = (dx, dy, dtheta) (eqs. 2-3)."""
    dist = jnp.hypot(u[..., 0], u[..., 1])
    sigma_d = params.alpha_d * dist
    sigma_theta = params.alpha_theta_d * dist + params.alpha_theta * jnp.abs(u[..., 2])
    return dist, sigma_d, sigma_theta


def world_step(pose: Array, u: Array) -> tuple[Array, Array]:
    """Delta d, the control's translation u[..., :2] turned into the world frame by the pose's
    heading: (x, y) components."""
    c, s = jnp.cos(pose[..., 2]), jnp.sin(pose[..., 2])
    return c * u[..., 0] - s * u[..., 1], s * u[..., 0] + c * u[..., 1]


def control_between(pose: Array, nxt: Array) -> Array:
    """The control u [..., 3] that takes ``pose`` to ``nxt`` (both [..., 3]) under eq. 1
    without noise, the inverse of ``world_step``: the translation turned into the frame of
    ``pose``, and the turn wrapped into (-pi, pi]."""
    c, s = jnp.cos(pose[..., 2]), jnp.sin(pose[..., 2])
    dx, dy = nxt[..., 0] - pose[..., 0], nxt[..., 1] - pose[..., 1]
    dth = nxt[..., 2] - pose[..., 2]
    return jnp.stack([c * dx + s * dy, -s * dx + c * dy, jnp.arctan2(jnp.sin(dth), jnp.cos(dth))],
                     -1)


def apply_motion(pose: Array, u: Array, eps: Array, params: MotionParams) -> Array:
    """Eq. 1 with standard-normal draws ``eps`` [..., 3] (along-track, heading, cross-track).

    pose [..., 3] and u [..., 3] broadcast against eps.
    """
    _, _, sigma_theta = motion_stds(u, params)
    scale = 1.0 + params.alpha_d * eps[..., 0]  # along-track noise: sigma_d / |d| = alpha_d
    cross = params.alpha_cross * eps[..., 2]  # cross-track noise: sigma_c / |d| = alpha_cross
    wx, wy = world_step(pose, u)
    dx = wx * scale - wy * cross
    dy = wy * scale + wx * cross
    dtheta = u[..., 2] + sigma_theta * eps[..., 1]
    return jnp.stack([pose[..., 0] + dx, pose[..., 1] + dy, pose[..., 2] + dtheta], axis=-1)


def sample_motion(key: Array, pose: Array, u: Array, params: MotionParams) -> Array:
    """Draw x_t ~ p(x_t | x_{t-1}, u_t) for every pose in the batch ``pose`` [J, 3]."""
    eps = jax.random.normal(key, pose.shape[:-1] + (3,), dtype=pose.dtype)
    return apply_motion(pose, u, eps, params)


def log_density(new_pose: Array, pose: Array, u: Array, params: MotionParams,
                min_std: float = 1e-6) -> Array:
    """log p(x_t | x_{t-1}, u_t) (eqs. 1-3) w.r.t. (along-track, cross-track, heading).

    With ``alpha_cross = 0`` the position noise lives on the line through Delta d, so the density
    is taken over the signed along-track displacement and the heading only (the cross-track term
    is left out, not evaluated at zero width). ``min_std`` keeps a zero control finite.
    """
    dist, sigma_d, sigma_theta = motion_stds(u, params)
    wx, wy = world_step(pose, u)
    safe = jnp.where(dist > 0, dist, 1.0)
    step_x, step_y = new_pose[..., 0] - pose[..., 0], new_pose[..., 1] - pose[..., 1]
    along = (step_x * wx + step_y * wy) / safe
    across = (step_y * wx - step_x * wy) / safe
    dtheta = new_pose[..., 2] - pose[..., 2] - u[..., 2]
    dtheta = jnp.arctan2(jnp.sin(dtheta), jnp.cos(dtheta))
    sd = jnp.maximum(sigma_d, min_std)
    st = jnp.maximum(sigma_theta, min_std)
    log_2pi = jnp.log(2.0 * jnp.pi)
    lp_d = -0.5 * ((along - dist) / sd) ** 2 - jnp.log(sd) - 0.5 * log_2pi
    lp_t = -0.5 * (dtheta / st) ** 2 - jnp.log(st) - 0.5 * log_2pi
    sc = jnp.maximum(params.alpha_cross * dist, min_std)
    lp_c = jnp.where(params.alpha_cross > 0,
                     -0.5 * (across / sc) ** 2 - jnp.log(sc) - 0.5 * log_2pi, 0.0)
    return lp_d + lp_t + lp_c
