"""GPS alignment (paper section 8 and appendix, eqs. A.1-A.10) and georeferenced outputs.

Each particle's SLAM path b_i (local frame) is fitted to GPS readings a_i (UTM site frame) by a
weighted orthogonal Procrustes fit with weights w_i = omega_i^2 = 1 / EPE_i^2; the SLAM estimate
itself is never changed. Batch form (A.1-A.8) and an online form with constant memory per
particle (A.9-A.10) give the same (R, l) after every reading.

Coordinates and precision: UTM northings are ~1e6-1e7 m, which float32 cannot hold to the metre.
The log reader therefore returns positions in a *site frame* (UTM minus a float64 ``origin``,
as in the paper's Fig. 12); everything in JAX works on site-frame metres, and host helpers add
the origin back in float64. WGS84 -> UTM uses the Krueger series in Karney's form (J. Geodesy
2011, terms to n^6, sub-millimetre within a UTM zone), implemented here in NumPy.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from gslam_jax.errors import InputError

__all__ = [
    "Alignment", "OnlineState", "align", "align_particles", "online_init", "online_update",
    "online_solve", "transform_points", "transform_poses", "interpolate_path",
    "GpsLog", "GpsLogError", "read_gps_log", "write_gps_log", "latlon_to_utm", "utm_to_latlon",
    "utm_zone", "utm_epsg", "transverse_mercator", "Ellipsoid", "WGS84",
    "align_to_gps", "readings_in_span", "map_corners", "world_file_params", "write_world_file",
    "write_georeferenced_png",
]

# Weighted spread of the SLAM positions (m^2) below which the rotation is undetermined.
_MIN_SPREAD_M2 = 1e-6


# --------------------------------------------------------------------------------------------
# Weighted orthogonal Procrustes (A.1-A.10)
# --------------------------------------------------------------------------------------------

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


def _clean(b: Array, a: Array, epe: Array, valid: Array) -> tuple[Array, Array, Array, Array, Array]:
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

    C_t = C_{t-1} + gamma_{t-1} (mu_{t-1} - mu_t)(nu_{t-1} - nu_t)^T + w_t (a_t - mu_t)(b_t - nu_t)^T.
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


# --------------------------------------------------------------------------------------------
# WGS84 -> UTM (transverse Mercator, Krueger series in Karney's form), NumPy float64
# --------------------------------------------------------------------------------------------

class Ellipsoid(NamedTuple):
    a: float   # equatorial radius, m
    f: float   # flattening


WGS84 = Ellipsoid(6378137.0, 1.0 / 298.257223563)


def _tm_coeffs(f: float) -> tuple[float, np.ndarray, np.ndarray]:
    """Rectifying radius / a and the alpha (forward) and beta (inverse) series to n^6."""
    n = f / (2.0 - f)
    n2, n3, n4, n5, n6 = n**2, n**3, n**4, n**5, n**6
    A = (1 + n2 / 4 + n4 / 64 + n6 / 256) / (1 + n)
    alpha = np.array([
        n / 2 - 2 * n2 / 3 + 5 * n3 / 16 + 41 * n4 / 180 - 127 * n5 / 288 + 7891 * n6 / 37800,
        13 * n2 / 48 - 3 * n3 / 5 + 557 * n4 / 1440 + 281 * n5 / 630 - 1983433 * n6 / 1935360,
        61 * n3 / 240 - 103 * n4 / 140 + 15061 * n5 / 26880 + 167603 * n6 / 181440,
        49561 * n4 / 161280 - 179 * n5 / 168 + 6601661 * n6 / 7257600,
        34729 * n5 / 80640 - 3418889 * n6 / 1995840,
        212378941 * n6 / 319334400])
    beta = np.array([
        n / 2 - 2 * n2 / 3 + 37 * n3 / 96 - n4 / 360 - 81 * n5 / 512 + 96199 * n6 / 604800,
        n2 / 48 + n3 / 15 - 437 * n4 / 1440 + 46 * n5 / 105 - 1118711 * n6 / 3870720,
        17 * n3 / 480 - 37 * n4 / 840 - 209 * n5 / 4480 + 5569 * n6 / 90720,
        4397 * n4 / 161280 - 11 * n5 / 504 - 830251 * n6 / 7257600,
        4583 * n5 / 161280 - 108847 * n6 / 3991680,
        20648693 * n6 / 638668800])
    return A, alpha, beta


def _conformal_tan(tau: np.ndarray, e: float) -> np.ndarray:
    """tan of the conformal latitude from tau = tan(phi) (Karney 2011, eq. 7-9)."""
    sig = np.sinh(e * np.arctanh(e * tau / np.hypot(1.0, tau)))
    return tau * np.hypot(1.0, sig) - sig * np.hypot(1.0, tau)


def transverse_mercator(lat: ArrayLike, lon: ArrayLike, lon0: float, k0: float = 0.9996,
                        lat0: float = 0.0, false_easting: float = 0.0,
                        false_northing: float = 0.0,
                        ellipsoid: Ellipsoid = WGS84) -> tuple[np.ndarray, np.ndarray]:
    """Forward transverse Mercator (degrees in, metres out), Krueger-Karney series to n^6."""
    a, f = ellipsoid
    e = math.sqrt(f * (2 - f))
    A, alpha, _ = _tm_coeffs(f)
    j = np.arange(1, 7)

    def xi_eta(phi: np.ndarray, lam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        tp = _conformal_tan(np.tan(phi), e)
        xi_p = np.arctan2(tp, np.cos(lam))
        eta_p = np.arcsinh(np.sin(lam) / np.hypot(tp, np.cos(lam)))
        x2, e2 = 2 * j * xi_p[..., None], 2 * j * eta_p[..., None]
        xi = xi_p + np.sum(alpha * np.sin(x2) * np.cosh(e2), -1)
        eta = eta_p + np.sum(alpha * np.cos(x2) * np.sinh(e2), -1)
        return xi, eta

    phi = np.radians(np.asarray(lat, np.float64))
    lam = np.radians(np.asarray(lon, np.float64) - lon0)
    lam = (lam + np.pi) % (2 * np.pi) - np.pi
    xi, eta = xi_eta(phi, lam)
    xi0, _ = xi_eta(np.radians(np.float64(lat0)), np.float64(0.0))
    return (false_easting + k0 * a * A * eta, false_northing + k0 * a * A * (xi - xi0))


def _tm_inverse(x: np.ndarray, y: np.ndarray, lon0: float, k0: float,
                ellipsoid: Ellipsoid) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of ``transverse_mercator`` with lat0 = 0 and no false origin (degrees out)."""
    a, f = ellipsoid
    e2 = f * (2 - f)
    e = math.sqrt(e2)
    A, _, beta = _tm_coeffs(f)
    j = np.arange(1, 7)
    xi, eta = y / (k0 * a * A), x / (k0 * a * A)
    x2, h2 = 2 * j * xi[..., None], 2 * j * eta[..., None]
    xi_p = xi - np.sum(beta * np.sin(x2) * np.cosh(h2), -1)
    eta_p = eta - np.sum(beta * np.cos(x2) * np.sinh(h2), -1)
    tau_p = np.sin(xi_p) / np.hypot(np.sinh(eta_p), np.cos(xi_p))
    lam = np.arctan2(np.sinh(eta_p), np.cos(xi_p))
    tau = tau_p.copy()
    for _ in range(5):  # Newton on tau'(tau) = tau_p (Karney 2011, eqs. 19-21); 2-3 suffice
        t1 = _conformal_tan(tau, e)
        tau = tau + (tau_p - t1) / np.hypot(1.0, t1) * (1 + (1 - e2) * tau**2) / (
            (1 - e2) * np.hypot(1.0, tau))
    return np.degrees(np.arctan(tau)), lon0 + np.degrees(lam)


UTM_LATITUDES = (-80.0, 84.0)  # UTM's defined range; beyond it the polar stereographic UPS


def utm_zone(lat: float, lon: float) -> int:
    """UTM zone number from longitude, with the Norway (32V) and Svalbard (31X-37X) exceptions."""
    lon = (lon + 180.0) % 360.0 - 180.0
    zone = int(math.floor((lon + 180.0) / 6.0)) % 60 + 1
    if 56.0 <= lat < 64.0 and 3.0 <= lon < 12.0:
        return 32
    if 72.0 <= lat < 84.0 and 0.0 <= lon < 42.0:
        return 31 if lon < 9.0 else 33 if lon < 21.0 else 35 if lon < 33.0 else 37
    return zone


def utm_epsg(zone: int, north: bool) -> int:
    """EPSG code of WGS84 / UTM zone (326zz north, 327zz south)."""
    return (32600 if north else 32700) + zone


def latlon_to_utm(lat: ArrayLike, lon: ArrayLike, zone: int | None = None,
                  north: bool | None = None) -> tuple[np.ndarray, np.ndarray, int, bool]:
    """WGS84 degrees -> UTM (easting, northing) metres in one zone (default: from the first
    point), returning (easting, northing, zone, north)."""
    lat, lon = np.asarray(lat, np.float64), np.asarray(lon, np.float64)
    outside = (lat < UTM_LATITUDES[0]) | (lat > UTM_LATITUDES[1])  # NaN is not outside
    if outside.any():
        raise ValueError(f"latitude {float(lat[outside].flat[0])} is outside UTM's range "
                         f"({-UTM_LATITUDES[0]:g} S to {UTM_LATITUDES[1]:g} N)")
    if zone is None:
        zone = utm_zone(float(lat.flat[0]), float(lon.flat[0]))
    if north is None:
        north = bool(lat.flat[0] >= 0)
    E, N = transverse_mercator(lat, lon, lon0=6.0 * zone - 183.0, k0=0.9996,
                               false_easting=500000.0,
                               false_northing=0.0 if north else 10000000.0)
    return E, N, zone, north


def utm_to_latlon(easting: ArrayLike, northing: ArrayLike, zone: int,
                  north: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """UTM metres -> WGS84 (lat, lon) degrees (inverse Krueger-Karney series, Newton)."""
    x = np.asarray(easting, np.float64) - 500000.0
    y = np.asarray(northing, np.float64) - (0.0 if north else 10000000.0)
    return _tm_inverse(x, y, 6.0 * zone - 183.0, 0.9996, WGS84)


# --------------------------------------------------------------------------------------------
# GPS logs
# --------------------------------------------------------------------------------------------

class GpsLogError(InputError):
    """A GPS log is malformed; the message names the file and line."""


class GpsLog(NamedTuple):
    """GPS readings in a UTM site frame (float64 NumPy).

    time [N] s; lat, lon [N] degrees; epe [N] m; xy [N,2] = UTM (E, N) - origin; origin (2,)
    the site-frame origin in UTM metres; zone, north the UTM zone; n_skipped the readings
    dropped while reading (NaN or out-of-range coordinates, EPE <= 0 or not finite).
    """

    time: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    epe: np.ndarray
    xy: np.ndarray
    origin: np.ndarray
    zone: int
    north: bool
    n_skipped: int = 0

    @property
    def epsg(self) -> int:
        return utm_epsg(self.zone, self.north)


_ALIASES = {
    "time": ("time", "t", "timestamp", "stamp", "sec", "secs", "seconds", "time_s"),
    "lat": ("lat", "latitude", "lat_deg"),
    "lon": ("lon", "lng", "long", "longitude", "lon_deg"),
    "epe": ("epe", "hepe", "epe_m", "sigma", "accuracy", "horizontal_accuracy", "eph"),
}


def _split(line: str) -> list[str]:
    line = line.strip()
    return [s.strip() for s in re.split(r"[,;\t]" if re.search(r"[,;\t]", line) else r"\s+",
                                        line)]


def read_gps_log(path: str | Path, origin: ArrayLike | None = None, zone: int | None = None,
                 strict: bool = False) -> GpsLog:
    """Read a text/CSV GPS log of (time, latitude, longitude, EPE) and convert to UTM.

    Separators: comma, semicolon, tab or whitespace; '#' starts a comment. An optional header
    line names the columns (e.g. ``time,lat,lon,epe``; common aliases accepted, extra columns
    ignored); without one the first four columns are taken in that order. Readings with a NaN
    or out-of-range coordinate or a non-positive/non-finite EPE are skipped and counted
    (``strict=True`` raises instead). The UTM zone comes from the first reading unless given;
    ``origin`` (UTM E, N) defaults to the first reading rounded to 100 m. Raises GpsLogError
    naming the file and line for unparsable lines, decreasing time, or < 2 usable readings.
    """
    path = Path(path)
    cols = {"time": 0, "lat": 1, "lon": 2, "epe": 3}
    rows: list[tuple[float, float, float, float]] = []
    skipped, seen_data = 0, False
    try:
        text = path.read_text()
    except OSError as err:
        raise GpsLogError(f"{path}: cannot read GPS log ({err})") from err
    last_t, last_line = -np.inf, 0
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        fields = _split(line)
        if not seen_data and not _is_number(fields[0]):
            names = [f.lower() for f in fields]
            cols = {}
            for key, aliases in _ALIASES.items():
                hit = [i for i, nm in enumerate(names) if nm in aliases]
                if not hit:
                    raise GpsLogError(f"{path}:{lineno}: header has no '{key}' column "
                                      f"(accepted names: {', '.join(aliases)}); got {fields}")
                cols[key] = hit[0]
            seen_data = True  # only one header line
            continue
        seen_data = True
        need = max(cols.values()) + 1
        if len(fields) < need:
            raise GpsLogError(f"{path}:{lineno}: expected at least {need} fields "
                              f"(time, lat, lon, epe), got {len(fields)}: {raw.strip()!r}")
        try:
            t, la, lo, ep = (float(fields[cols[k]]) for k in ("time", "lat", "lon", "epe"))
        except ValueError:
            raise GpsLogError(f"{path}:{lineno}: not a number in {raw.strip()!r}") from None
        if not math.isfinite(t):
            raise GpsLogError(f"{path}:{lineno}: time is not finite ({fields[cols['time']]})")
        if t < last_t:
            raise GpsLogError(f"{path}:{lineno}: time {t} goes backwards "
                              f"(line {last_line} had {last_t})")
        last_t, last_line = t, lineno
        bad = None
        if not (math.isfinite(la) and math.isfinite(lo)):
            bad = "non-finite coordinate"
        elif not (-90.0 <= la <= 90.0 and -180.0 <= lo <= 360.0):
            bad = f"coordinate out of range (lat {la}, lon {lo})"
        elif not (math.isfinite(ep) and ep > 0):
            bad = f"EPE must be positive and finite, got {ep}"
        if bad is None and not UTM_LATITUDES[0] <= la <= UTM_LATITUDES[1]:
            raise GpsLogError(f"{path}:{lineno}: latitude {la} is outside UTM's range "
                              f"({-UTM_LATITUDES[0]:g} S to {UTM_LATITUDES[1]:g} N); polar "
                              "sites need UPS, which gslam does not implement")
        if bad is not None:
            if strict:
                raise GpsLogError(f"{path}:{lineno}: {bad}")
            skipped += 1
            continue
        rows.append((t, la, lo, ep))
    if len(rows) < 2:
        raise GpsLogError(f"{path}: need at least 2 usable GPS readings, found {len(rows)} "
                          f"({skipped} skipped)")
    arr = np.asarray(rows, np.float64)
    E, N, zone, north = latlon_to_utm(arr[:, 1], arr[:, 2], zone=zone)
    if origin is None:
        origin = np.round(np.array([E[0], N[0]]) / 100.0) * 100.0
    origin = np.asarray(origin, np.float64)
    xy = np.stack([E, N], -1) - origin
    return GpsLog(arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3], xy, origin, zone, north, skipped)


def _is_number(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def write_gps_log(path: str | Path, time: ArrayLike, lat: ArrayLike, lon: ArrayLike,
                  epe: ArrayLike) -> None:
    """Write a CSV GPS log with header ``time,lat,lon,epe`` (readable by ``read_gps_log``)."""
    arr = np.stack([np.asarray(v, np.float64) for v in (time, lat, lon, epe)], -1)
    np.savetxt(path, arr, delimiter=",", header="time,lat,lon,epe", comments="",
               fmt=["%.3f", "%.9f", "%.9f", "%.3f"])


# --------------------------------------------------------------------------------------------
# Host-side pipeline helpers and georeferenced outputs
# --------------------------------------------------------------------------------------------

def align_to_gps(slam_times: ArrayLike, paths: ArrayLike, gps_time: ArrayLike,
                 gps_xy: ArrayLike, gps_epe: ArrayLike) -> tuple[Alignment, Array]:
    """Align SLAM paths [T,2] or [J,T,2] (times [T], same clock as the GPS) to GPS readings in
    the site frame; paths are interpolated at the GPS times and readings outside the SLAM time
    span (``readings_in_span``) are masked. Returns (Alignment, aligned paths) like
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
    al, aligned = _align_interpolated(st, paths, gt, jnp.asarray(gps_xy, jnp.float32),
                                      jnp.asarray(gps_epe, jnp.float32))
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
                        epe: Array) -> tuple[Alignment, Array]:
    b = jax.vmap(lambda p: interpolate_path(st, p, gt)[0])(paths)
    inside = (gt >= st[0]) & (gt <= st[-1])
    al = jax.vmap(align, in_axes=(0, None, None, None))(b, a, epe, inside)
    return al, jax.vmap(transform_points)(al, paths)


def map_corners(map_origin: tuple[float, float], resolution: float,
                map_shape: tuple[int, int]) -> np.ndarray:
    """SLAM-frame corners [4,2] of a map whose cell (i, j) covers x0 + i res, y0 + j res
    (FilterConfig convention), counter-clockwise from (x0, y0)."""
    x0, y0 = map_origin
    w, h = map_shape[0] * resolution, map_shape[1] * resolution
    return np.array([[x0, y0], [x0 + w, y0], [x0 + w, y0 + h], [x0, y0 + h]], np.float64)


def world_file_params(map_origin: tuple[float, float], resolution: float,
                      map_shape: tuple[int, int], R: ArrayLike, l: ArrayLike,
                      site_origin: ArrayLike = (0.0, 0.0)) -> np.ndarray:
    """The six world-file numbers (A, D, B, E, C, F) for a north-up PNG of the map.

    The PNG is ``np.flipud(grid.T)`` of a grid [nx, ny] (cell (i, j) -> column i, row
    ny-1-j). A GIS maps pixel (col, row) to X = A col + B row + C, Y = D col + E row + F, with
    (C, F) the centre of the top-left pixel, in UTM metres (site frame + ``site_origin``).
    """
    R, l = np.asarray(R, np.float64), np.asarray(l, np.float64)
    res, ny = float(resolution), int(map_shape[1])
    top_left = np.array([map_origin[0] + 0.5 * res, map_origin[1] + (ny - 0.5) * res])
    C, F = R @ top_left + l + np.asarray(site_origin, np.float64)
    A, D = R[:, 0] * res     # +1 column = +res along SLAM x
    B, E = -R[:, 1] * res    # +1 row = -res along SLAM y
    return np.array([A, D, B, E, C, F])


def write_world_file(path: str | Path, params: ArrayLike) -> Path:
    """Write six world-file lines (``.pgw`` beside a PNG); returns the path."""
    path = Path(path)
    path.write_text("".join(f"{v:.10f}\n" for v in np.asarray(params, np.float64)))
    return path


def write_georeferenced_png(png_path: str | Path, grid: ArrayLike,
                            map_origin: tuple[float, float], resolution: float,
                            R: ArrayLike, l: ArrayLike, site_origin: ArrayLike = (0.0, 0.0),
                            cmap: str = "viridis", vmin: float | None = None,
                            vmax: float | None = None) -> tuple[Path, Path]:
    """Save grid [nx, ny] (e.g. expected std per cell, NaN = unknown) as a north-up PNG plus a
    ``.pgw`` world file placing it in UTM via the alignment (R, l). Returns both paths."""
    from matplotlib.image import imsave  # no pyplot: leaves the user's backend alone

    png_path = Path(png_path)
    grid = np.asarray(grid, np.float64)
    # Masked, so NaN cells are transparent and do not spoil the colour scale.
    imsave(png_path, np.ma.masked_invalid(np.flipud(grid.T)), cmap=cmap, vmin=vmin, vmax=vmax)
    params = world_file_params(map_origin, resolution, grid.shape, R, l, site_origin)
    return png_path, write_world_file(png_path.with_suffix(".pgw"), params)
