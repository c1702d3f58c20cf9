"""WGS84 <-> UTM: transverse Mercator by the Krueger series in Karney's form (NumPy float64).

Karney (J. Geodesy 2011), terms to n^6: sub-millimetre within a UTM zone, so the projection adds
nothing measurable to GPS errors of metres. Float64 NumPy on the host, because UTM coordinates
need more digits than float32 holds.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from jax.typing import ArrayLike

__all__ = [
    "Ellipsoid", "WGS84", "UTM_LATITUDES", "transverse_mercator", "latlon_to_utm",
    "utm_to_latlon", "utm_zone", "utm_epsg",
]

class Ellipsoid(NamedTuple):
    """A reference ellipsoid."""

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
