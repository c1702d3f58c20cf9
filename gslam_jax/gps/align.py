"""Weighted orthogonal Procrustes alignment of SLAM paths to GPS readings (paper appendix).

Each particle's SLAM path b_i (local frame) is fitted to GPS readings a_i (UTM site frame) by a
weighted orthogonal Procrustes fit with weights w_i = omega_i^2 = 1 / EPE_i^2 (eqs. A.1-A.8);
the SLAM estimate itself is never changed. The online form (A.9-A.10) keeps constant memory per
particle and gives the same (R, l) after every reading as the batch form.

Positions are site-frame metres (UTM minus a float64 origin, see ``gps.log``): UTM northings
(~1e6-1e7 m) do not fit float32 to the metre, site-frame offsets do.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

__all__ = [
    "Alignment", "OnlineState", "align", "align_particles", "online_init", "online_update",
    "online_solve", "transform_points", "transform_poses", "interpolate_path", "align_to_gps",
    "readings_in_span",
]

# Weighted spread of the SLAM positions (m^2) below which the rotation is undetermined.
_MIN_SPREAD_M2 = 1e-6


class Alignment(NamedTuple):
    """SLAM -> GPS rigid transform a ~ R b + l (eq. A.1); fields gain leading axes under vmap.

    cost: eq. A.1 at the optimum, sum_i ||a_i - (R b_i + l)||^2 / EPE_i^2.
    n_used: readings that entered the fit; n_skipped: readings marked valid but dropped for
        a non-finite coordinate or EPE, or EPE <= 0.
    ok: at least two readings and a SLAM path that is not a single point (else R is arbitrary).
    """

    R: Array
    l: Array
    cost: Array
    n_used: Array
    n_skipped: Array
    ok: Array


class OnlineState(NamedTuple):
    """Running sums of eqs. A.9-A.10 (constant memory: 13 numbers per particle).

    alpha = sum w a, beta = sum w b, gamma = sum w (A.9); C = [A Omega^2 B^T]_t, the centred
    weighted cross-covariance (A.10); saa, sbb = sum w |a - mu|^2, sum w |b - nu|^2 (same
    update rule as C, they give the eq. A.1 cost).
    """

    alpha: Array
    beta: Array
    gamma: Array
    C: Array
    saa: Array
    sbb: Array
    n_used: Array
    n_skipped: Array


def _clean(b: Array, a: Array, epe: Array,
           valid: Array) -> tuple[Array, Array, Array, Array, Array]:
    """Weights w = 1/EPE^2 (eq. A.2) with bad readings zero-weighted and their values made safe."""
    good = valid & jnp.all(jnp.isfinite(a), -1) & jnp.all(jnp.isfinite(b), -1)
    good = good & jnp.isfinite(epe) & (epe > 0)
    # Safe substitutes inside where(): 0 * NaN would otherwise poison the sums.
    w = jnp.where(good, 1.0 / jnp.where(good, epe, 1.0) ** 2, 0.0)
    a = jnp.where(good[..., None], a, 0.0)
    b = jnp.where(good[..., None], b, 0.0)
    skipped = jnp.sum(valid & ~good, dtype=jnp.int32)
    return b, a, w, good, skipped


def _rotation(C: Array) -> Array:
    """Eqs. A.6-A.8: R = U diag(1, det(U V^T)) V^T from the SVD of C = A Omega^2 B^T."""
    U, _, Vt = jnp.linalg.svd(C)
    d = jnp.where(jnp.linalg.det(U @ Vt) < 0, -1.0, 1.0).astype(C.dtype)
    return (U * jnp.stack([jnp.ones_like(d), d])) @ Vt


def _solve(C: Array, mu: Array, nu: Array, saa: Array, sbb: Array, gamma: Array,
           n_used: Array, n_skipped: Array) -> Alignment:
    R = _rotation(C)
    l = mu - R @ nu  # the optimal transform maps nu to mu (text after eq. A.2)
    cost = jnp.maximum(saa + sbb - 2.0 * jnp.sum(R * C), 0.0)
    ok = (n_used >= 2) & (sbb > _MIN_SPREAD_M2 * gamma)
    return Alignment(R, l, cost, n_used, n_skipped, ok)


def align(b: ArrayLike, a: ArrayLike, epe: ArrayLike, valid: ArrayLike | None = None) -> Alignment:
    """Batch alignment (eqs. A.1-A.8) of one SLAM path b [T,2] to GPS readings a [T,2].

    epe [T] is the receiver's horizontal EPE (weights 1/EPE^2); valid [T] masks readings
    (default all). Non-finite values and EPE <= 0 are skipped and counted. Jit- and vmap-able.
    """
    b, a, epe = jnp.asarray(b), jnp.asarray(a), jnp.asarray(epe)
    dtype = jnp.result_type(b.dtype, a.dtype, epe.dtype, jnp.float32)
    b, a, epe = b.astype(dtype), a.astype(dtype), epe.astype(dtype)
    valid = jnp.ones(epe.shape, bool) if valid is None else jnp.asarray(valid, bool)
    b, a, w, good, skipped = _clean(b, a, epe, valid)
    gamma = jnp.sum(w)
    g_safe = jnp.where(gamma > 0, gamma, 1.0)
    mu = jnp.sum(w[:, None] * a, 0) / g_safe                     # eq. A.2
    nu = jnp.sum(w[:, None] * b, 0) / g_safe
    ac = jnp.where(good[:, None], a - mu, 0.0)                     # eq. A.3
    bc = jnp.where(good[:, None], b - nu, 0.0)
    C = (w[:, None] * ac).T @ bc                                   # A Omega^2 B^T, eq. A.6
    saa = jnp.sum(w * jnp.sum(ac * ac, -1))
    sbb = jnp.sum(w * jnp.sum(bc * bc, -1))
    return _solve(C, mu, nu, saa, sbb, gamma, jnp.sum(good, dtype=jnp.int32), skipped)


def align_particles(paths: ArrayLike, a: ArrayLike, epe: ArrayLike,
                    valid: ArrayLike | None = None) -> tuple[Alignment, Array]:
    """Align every particle's path [J,T,2] to the same GPS readings; returns (Alignment with a
    leading J axis, the aligned paths [J,T,2] in the GPS frame)."""
    paths = jnp.asarray(paths)
    al = jax.vmap(align, in_axes=(0, None, None, None))(paths, a, epe, valid)
    return al, jax.vmap(transform_points)(al, paths)


def online_init(batch_shape: tuple[int, ...] = (), dtype: jnp.dtype = jnp.float32) -> OnlineState:
    """Empty running sums of eq. A.9 (t = 0), optionally with leading particle axes."""
    z = lambda *s: jnp.zeros(batch_shape + s, dtype)  # noqa: E731
    zi = jnp.zeros(batch_shape, jnp.int32)
    return OnlineState(z(2), z(2), z(), z(2, 2), z(), z(), zi, zi)


def online_update(state: OnlineState, b_i: ArrayLike, a_i: ArrayLike, epe_i: ArrayLike,
                  valid: ArrayLike = True) -> OnlineState:
    """Add one reading: eq. A.10 update of alpha, beta, gamma, mu, nu and A Omega^2 B^T.

    C_t = C_{t-1} + gamma_{t-1} (mu_{t-1} - mu_t)(nu_{t-1} - nu_t)^T
          + w_t (a_t - mu_t)(b_t - nu_t)^T.
    A reading that is invalid (mask, non-finite, EPE <= 0) leaves the sums unchanged.
    For particles, vmap with in_axes=(0, 0, None, None[, None]).
    """
    dtype = state.gamma.dtype
    b, a, w, good, skipped = _clean(jnp.asarray(b_i, dtype)[None], jnp.asarray(a_i, dtype)[None],
                                    jnp.asarray(epe_i, dtype)[None],
                                    jnp.asarray(valid, bool)[None])
    b, a, w, good = b[0], a[0], w[0], good[0]

    def mean(s: Array, g: Array) -> Array:
        return jnp.where(g > 0, s / jnp.where(g > 0, g, 1.0), 0.0)

    mu0, nu0 = mean(state.alpha, state.gamma), mean(state.beta, state.gamma)
    alpha, beta, gamma = state.alpha + w * a, state.beta + w * b, state.gamma + w
    mu, nu = mean(alpha, gamma), mean(beta, gamma)
    dmu, dnu = mu0 - mu, nu0 - nu
    ac = jnp.where(good, a - mu, 0.0)
    bc = jnp.where(good, b - nu, 0.0)
    C = state.C + state.gamma * jnp.outer(dmu, dnu) + w * jnp.outer(ac, bc)
    saa = state.saa + state.gamma * dmu @ dmu + w * ac @ ac
    sbb = state.sbb + state.gamma * dnu @ dnu + w * bc @ bc
    return OnlineState(alpha, beta, gamma, C, saa, sbb,
                       state.n_used + good.astype(jnp.int32), state.n_skipped + skipped)


def online_solve(state: OnlineState) -> Alignment:
    """(R, l) from the running sums via eqs. A.6-A.8 (vmap for particles)."""
    g_safe = jnp.where(state.gamma > 0, state.gamma, 1.0)
    mu = jnp.where(state.gamma > 0, state.alpha / g_safe, 0.0)
    nu = jnp.where(state.gamma > 0, state.beta / g_safe, 0.0)
    return _solve(state.C, mu, nu, state.saa, state.sbb, state.gamma, state.n_used,
                  state.n_skipped)


def transform_points(al: Alignment, xy: ArrayLike) -> Array:
    """SLAM-frame points [..., 2] -> GPS (site) frame: R b + l."""
    return jnp.asarray(xy) @ al.R.T + al.l


def transform_poses(al: Alignment, poses: ArrayLike) -> Array:
    """SLAM-frame poses [..., 3] (x, y, theta) -> GPS frame; heading gains the rotation angle."""
    poses = jnp.asarray(poses)
    dtheta = jnp.arctan2(al.R[1, 0], al.R[0, 0])
    theta = poses[..., 2] + dtheta
    theta = jnp.arctan2(jnp.sin(theta), jnp.cos(theta))
    return jnp.concatenate([transform_points(al, poses[..., :2]), theta[..., None]], -1)


def interpolate_path(times: ArrayLike, xy: ArrayLike, query: ArrayLike) -> tuple[Array, Array]:
    """Positions of a path xy [T,2] (times [T], increasing) at query times [N], linearly
    interpolated; returns (xy [N,2], inside [N]) where inside marks queries within the path."""
    times, xy, query = jnp.asarray(times), jnp.asarray(xy), jnp.asarray(query)
    out = jnp.stack([jnp.interp(query, times, xy[:, k]) for k in range(2)], -1)
    return out, (query >= times[0]) & (query <= times[-1])


def align_to_gps(slam_times: ArrayLike, paths: ArrayLike, gps_time: ArrayLike,
                 gps_xy: ArrayLike, gps_epe: ArrayLike,
                 keep: ArrayLike | None = None) -> tuple[Alignment, Array]:
    """Align SLAM paths [T,2] or [J,T,2] (times [T], same clock as the GPS) to GPS readings in
    the site frame; paths are interpolated at the GPS times and readings outside the SLAM time
    span (``readings_in_span``), or not in ``keep`` [N] (default all), are masked. Returns (Alignment, aligned paths) like
    ``align_particles``: ``Alignment.n_used`` counts the readings in the fit and ``cost`` is its
    weighted residual. Raises ValueError if fewer than two readings are usable or the path does
    not move."""
    paths = jnp.asarray(paths, jnp.float32)
    single = paths.ndim == 2
    paths = paths[None] if single else paths
    # Times relative to the first frame keep float32 interpolation exact enough (epoch ~1e9 s).
    t0 = float(np.asarray(slam_times)[0])
    st = jnp.asarray(np.asarray(slam_times, np.float64) - t0, jnp.float32)
    gt = jnp.asarray(np.asarray(gps_time, np.float64) - t0, jnp.float32)
    keep = jnp.ones(gt.shape, bool) if keep is None else jnp.asarray(keep, bool)
    al, aligned = _align_interpolated(st, paths, gt, jnp.asarray(gps_xy, jnp.float32),
                                      jnp.asarray(gps_epe, jnp.float32), keep)
    n_used = int(np.max(np.asarray(al.n_used)))
    if n_used < 2:
        raise ValueError(f"GPS alignment needs at least 2 usable readings within the SLAM time "
                         f"span [{t0:.3f}, {t0 + float(st[-1]):.3f}] s; got {n_used} "
                         f"({int(np.max(np.asarray(al.n_skipped)))} skipped)")
    if not bool(np.all(np.asarray(al.ok))):
        raise ValueError("GPS alignment is undetermined: the SLAM path does not move during "
                         "the GPS readings")
    if single:
        return jax.tree.map(lambda x: x[0], al), aligned[0]
    return al, aligned


def readings_in_span(slam_times: ArrayLike, gps_time: ArrayLike) -> np.ndarray:
    """Mask [N] of the GPS readings whose times lie in the SLAM time span [t_0, t_{T-1}] (same
    clock): the readings ``align_to_gps`` can use. NumPy float64, no JAX work."""
    st = np.asarray(slam_times, np.float64)
    gt = np.asarray(gps_time, np.float64)
    return (gt >= st[0]) & (gt <= st[-1])


@jax.jit
def _align_interpolated(st: Array, paths: Array, gt: Array, a: Array,
                        epe: Array, keep: Array) -> tuple[Alignment, Array]:
    b = jax.vmap(lambda p: interpolate_path(st, p, gt)[0])(paths)
    inside = (gt >= st[0]) & (gt <= st[-1]) & keep
    al = jax.vmap(align, in_axes=(0, None, None, None))(b, a, epe, inside)
    return al, jax.vmap(transform_points)(al, paths)
