"""The reference filter's own math in NumPy: motion (eqs. 1-3), eq. 26, eqs. 30/31, ESS, resamplers.

Written from the paper, independently of the dense filter's modules. Poses and maps are float32
so that the discrete decisions (which map cell a local cell lands in) are the same as the dense
filter's; the log-gamma weights are evaluated in float64 from those float32 statistics.

Float32 cos and sin come from the C library (``cosf``/``sinf``), which is what XLA:CPU calls too:
NumPy's own float32 SIMD trigonometry differs from it in the last bit for ~15 % of arguments, and
a one-ulp pose difference moves cells across cell boundaries.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import math
from typing import Callable

import numpy as np

__all__ = ["cos32", "sin32", "hypot32", "apply_motion", "lgamma_half", "log_predictive",
           "combine", "ess", "RESAMPLERS", "resample", "survivors_keep_slots", "LOG_W_ROUNDING",
           "ESS_ROUNDING", "THRESHOLD_TIE", "resample_threshold", "decision_within_rounding",
           "cdf_rounding", "follow_ancestors"]

F32 = np.float32


def _libm() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("m") or "libm.so.6"
    try:
        lib = ctypes.CDLL(name)
        for fn in (lib.cosf, lib.sinf):
            fn.restype, fn.argtypes = ctypes.c_float, [ctypes.c_float]
        return lib
    except (OSError, AttributeError):
        return None


_LIBM = _libm()
_COSF = np.frompyfunc(_LIBM.cosf, 1, 1) if _LIBM else None
_SINF = np.frompyfunc(_LIBM.sinf, 1, 1) if _LIBM else None


def cos32(x: np.ndarray) -> np.ndarray:
    """float32 cosine as the C library computes it (falls back to NumPy without libm)."""
    x = np.asarray(x, F32)
    return _COSF(x).astype(F32) if _COSF is not None else np.cos(x)


def sin32(x: np.ndarray) -> np.ndarray:
    """float32 sine as the C library computes it (falls back to NumPy without libm)."""
    x = np.asarray(x, F32)
    return _SINF(x).astype(F32) if _SINF is not None else np.sin(x)


def hypot32(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Overflow-safe float32 hypotenuse: hi * sqrt(1 + (lo / hi)^2)."""
    a, b = np.abs(np.asarray(a, F32)), np.abs(np.asarray(b, F32))
    hi, lo = np.maximum(a, b), np.minimum(a, b)
    safe = np.where(hi == 0, F32(1), hi)
    return np.where(hi == 0, hi, hi * np.sqrt(F32(1) + np.square(lo / safe)))


def apply_motion(pose: np.ndarray, u: np.ndarray, eps: np.ndarray, alpha_d: float,
                 alpha_theta_d: float, alpha_theta: float, alpha_cross: float = 0.0
                 ) -> np.ndarray:
    """Eq. 1 for poses [J, 3] (float32) with standard-normal draws eps [J, 3].

    The position noise along the VO translation has sigma_d = alpha_d |d| (eq. 2), so it scales
    the translation by (1 + alpha_d eps_0); across it, alpha_cross |d| eps_2 along the
    translation turned by +90 degrees; heading noise has sigma_theta = alpha_theta_d |d| +
    alpha_theta |dtheta| (eq. 3).
    """
    pose, u, eps = np.asarray(pose, F32), np.asarray(u, F32), np.asarray(eps, F32)
    dist = hypot32(u[0], u[1])
    sigma_theta = F32(alpha_theta_d) * dist + F32(alpha_theta) * np.abs(u[2])
    scale = F32(1) + F32(alpha_d) * eps[:, 0]
    side = F32(alpha_cross) * eps[:, 2]
    c, s = cos32(pose[:, 2]), sin32(pose[:, 2])
    tx, ty = c * u[0] - s * u[1], s * u[0] + c * u[1]
    dx = tx * scale - ty * side
    dy = ty * scale + tx * side
    dth = u[2] + sigma_theta * eps[:, 1]
    return np.stack([pose[:, 0] + dx, pose[:, 1] + dy, pose[:, 2] + dth], axis=-1).astype(F32)


def lgamma_half(k: np.ndarray) -> np.ndarray:
    """lgamma(k / 2) in float64, evaluated once per distinct value (k is integer-valued)."""
    k = np.asarray(k, np.float64)
    if k.size == 0:
        return np.zeros_like(k)
    vals, inv = np.unique(k, return_inverse=True)
    table = np.array([math.lgamma(0.5 * v) for v in vals])
    return table[inv].reshape(k.shape)


def log_predictive(k: np.ndarray, S: np.ndarray, kp: np.ndarray, Sp: np.ndarray) -> np.ndarray:
    """Log posterior predictive of the observed variance v = S / k given the prior (k', S')
    (eqs. 18, 26), float64, for k, k' > 0:

    lgamma(k''/2) - lgamma(k/2) - lgamma(k'/2) + [k log S + k' log S' - k'' log S''] / 2 - log v.
    """
    k, S, kp, Sp = (np.asarray(a, np.float64) for a in (k, S, kp, Sp))
    k2, S2 = k + kp, S + Sp
    return (lgamma_half(k2) - lgamma_half(k) - lgamma_half(kp)
            + 0.5 * (k * np.log(S) + kp * np.log(Sp) - k2 * np.log(S2)) - np.log(S / k))


def combine(sum_prev: float, n_prev: int, sum_new: float, n_obs: int, beta_prev: float,
            beta_new: float, mode: str) -> float:
    """Tempered log importance factor of one particle from its per-cell sums.

    "ignore" (eq. 30): sum over previously seen cells / (beta_prev * N_prev), 0 if none.
    "sample" (eq. 31): (sum_prev / beta_prev + sum_new / beta_new) / N_obs.
    """
    if mode == "ignore":
        return sum_prev / (beta_prev * n_prev) if n_prev > 0 else 0.0
    return (sum_prev / beta_prev + sum_new / beta_new) / max(n_obs, 1)


def tempering_exponent(log_w: np.ndarray, log_lam: np.ndarray, target: float,
                       tol: float = 1e-10) -> float:
    """Adaptive tempering, written apart from ``gslam_jax.rbpf.tempering``: the largest
    exponent phi in [0, 1] of the increments ``log_lam`` whose conditional ESS fraction
    ``(sum W e^{phi l})^2 / sum W e^{2 phi l}`` under the weights W = exp(log_w) is at least
    ``target``; 1 when phi = 1 meets it. In float64, by the Illinois (modified regula falsi)
    method on g(phi) = log CESS(phi) - log target, which falls monotonically from g(0) >= 0."""
    w = np.exp(np.asarray(log_w, np.float64))
    lam = np.where(w > 0, np.asarray(log_lam, np.float64), 0.0)

    def g(phi: float) -> float:
        x = phi * lam
        a, b = x.max(), (2.0 * x).max()
        return (2.0 * (a + np.log(np.sum(w * np.exp(x - a))))
                - (b + np.log(np.sum(w * np.exp(2.0 * x - b)))) - math.log(target))

    g1 = g(1.0)
    if g1 >= 0.0:
        return 1.0
    lo, hi, g_lo, g_hi, side = 0.0, 1.0, g(0.0), g1, 0
    while hi - lo > tol:
        phi = (lo * g_hi - hi * g_lo) / (g_hi - g_lo)
        if not lo < phi < hi:
            phi = 0.5 * (lo + hi)
        gp = g(phi)
        if gp >= 0.0:
            lo, g_lo = phi, gp
            if side == -1:
                g_hi *= 0.5
            side = -1
        else:
            hi, g_hi = phi, gp
            if side == 1:
                g_lo *= 0.5
            side = 1
        if gp == 0.0:
            break
    return lo


def ess(log_w: np.ndarray) -> float:
    """Effective sample size 1 / sum w^2 of normalised log weights (eq. 23)."""
    return float(1.0 / np.sum(np.exp(2.0 * np.asarray(log_w, np.float64))))


# An ESS within this fraction above ratio * J counts as at the threshold (resampled): adaptive
# tempering puts the ESS there exactly, and float rounding must not decide.
THRESHOLD_TIE = 1e-3
# How far another filter's float32 normalised log weights may lie from these float64 ones by
# rounding alone (``gslam compare``'s tolerance on them). Weights off by at most d in the log
# put the ESS off by a factor within e^(+-4d) (sum w^2 over (sum w)^2), and a cumulative weight
# off by at most d/2 (A e^d / (A e^d + (1 - A) e^-d) - A <= d/2 for A in [0, 1]).
LOG_W_ROUNDING = 1e-4
ESS_ROUNDING = 4.0 * LOG_W_ROUNDING


def resample_threshold(ratio: float, J: int) -> float:
    """The ESS below which the filter resamples (eq. 23), the tie band included."""
    return ratio * J * (1.0 + THRESHOLD_TIE)


def decision_within_rounding(ess_value: float, threshold: float) -> bool:
    """Whether an ESS lies so near ``threshold`` that a float32 filter's ESS may fall on the
    other side of it by rounding alone (within a relative ESS_ROUNDING)."""
    return abs(ess_value - threshold) <= ESS_ROUNDING * threshold


def cdf_rounding(J: int) -> float:
    """How far a float32 filter's normalised cumulative weight may lie from the float64 one:
    LOG_W_ROUNDING / 2 from its weights, plus its float32 sum of J terms (J eps32)."""
    return 0.5 * LOG_W_ROUNDING + J * float(np.finfo(F32).eps)


def _positions(scheme: str, u: np.ndarray) -> np.ndarray | None:
    """The points in [0, 1) at which an inverse-CDF scheme reads the cumulative weights, in
    the order of its draws; None for a scheme that is not one (residual)."""
    J = u.size
    if scheme == "multinomial":
        return u
    if scheme == "systematic":
        return (np.arange(J) + u[0]) / J
    if scheme == "stratified":
        return (np.arange(J) + u) / J
    return None


def follow_ancestors(scheme: str, w: np.ndarray, u: np.ndarray, target: np.ndarray
                     ) -> tuple[np.ndarray, int, float] | None:
    """Another filter's ancestors ``target`` [J] (arranged by ``survivors_keep_slots``) when
    they differ from this one's draws only by rounding of the cumulative weights.

    An inverse CDF assigns the sorted draw positions to particles in increasing order, so
    ``target``'s offspring counts fix which particle each sorted position went to (the
    arrangement depends on the counts alone). They are rounding when every position lies
    within ``cdf_rounding`` of the interval of the particle it went to.

    Returns (ancestors, draws that went elsewhere than here, largest distance of one from its
    particle's interval), or None when ``target`` needs a draw further than rounding explains
    (a real difference) or the scheme is not an inverse CDF (residual)."""
    w = np.asarray(w, np.float64)
    u = np.asarray(u, np.float64)
    target = np.asarray(target, np.int64)
    pos = _positions(scheme, u)
    if pos is None:
        return None
    J = w.size
    cdf = np.cumsum(w)
    cdf = cdf / cdf[-1]
    lower = np.concatenate([[0.0], cdf[:-1]])  # particle j covers [lower[j], cdf[j])
    p = np.sort(pos)
    went = np.repeat(np.arange(J), np.bincount(target, minlength=J))
    here = np.clip(np.searchsorted(cdf, p, side="right"), 0, J - 1)
    outside = np.maximum(np.maximum(lower[went] - p, p - cdf[went]), 0.0)
    anc = survivors_keep_slots(went)
    if outside.max() > cdf_rounding(J) or not np.array_equal(anc, target):
        return None  # too far, or not the arrangement of its own counts
    moved = went != here
    return anc, int(moved.sum()), float(outside[moved].max()) if moved.any() else 0.0


def _inverse_cdf(w: np.ndarray, positions: np.ndarray) -> np.ndarray:
    cdf = np.cumsum(w)
    cdf = cdf / cdf[-1]
    return np.clip(np.searchsorted(cdf, positions, side="right"), 0, w.size - 1)


def _multinomial(w: np.ndarray, u: np.ndarray) -> np.ndarray:
    return _inverse_cdf(w, u)


def _systematic(w: np.ndarray, u: np.ndarray) -> np.ndarray:
    return _inverse_cdf(w, (np.arange(w.size) + u[0]) / w.size)


def _stratified(w: np.ndarray, u: np.ndarray) -> np.ndarray:
    return _inverse_cdf(w, (np.arange(w.size) + u) / w.size)


def _residual(w: np.ndarray, u: np.ndarray) -> np.ndarray:
    """floor(J w_j) copies in order, then slot i >= their total takes a draw u_i from the
    renormalised residuals J w_j - floor(J w_j)."""
    J = w.size
    copies = np.floor(J * w)
    frac = J * w - copies
    det = np.repeat(np.arange(J), copies.astype(int))
    rest = _inverse_cdf(frac if frac.sum() > 0 else np.ones(J), u)
    out = rest.copy()
    out[:det.size] = det[:J]
    return out


RESAMPLERS: dict[str, Callable[[np.ndarray, np.ndarray], np.ndarray]] = {
    "multinomial": _multinomial, "systematic": _systematic,
    "stratified": _stratified, "residual": _residual}


def resample(scheme: str, w: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Ancestor indices [J] for normalised weights w from the uniforms u [J]."""
    if scheme not in RESAMPLERS:
        raise ValueError(f"unknown resampler '{scheme}'; choose one of {sorted(RESAMPLERS)}")
    return RESAMPLERS[scheme](np.asarray(w, np.float64), np.asarray(u, np.float64)).astype(np.int64)


def survivors_keep_slots(anc: np.ndarray) -> np.ndarray:
    """Rearrange ancestors as the dense filter does before its in-place copy: a particle with
    offspring keeps its own slot; the slots of particles without offspring, in increasing
    order, take the remaining copies, parents in increasing order."""
    anc = np.asarray(anc, np.int64)
    J = anc.size
    counts = np.bincount(anc, minlength=J)
    out = np.arange(J)
    extra = [p for p in range(J) for _ in range(max(counts[p] - 1, 0))]
    dead = [i for i in range(J) if counts[i] == 0]
    for slot, parent in zip(dead, extra, strict=True):
        out[slot] = parent
    return out
