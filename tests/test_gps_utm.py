"""WGS84 -> UTM (Krueger-Karney series) against published examples and independent formulas;
the GPS log reader's header handling, skipping, counting and error messages."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from gslam_jax import gps


def _snyder_tm(lat, lon, lon0, k0=0.9996, a=6378137.0, f=1 / 298.257223563):
    """Snyder (USGS PP 1395, 1987) eqs. 8-9, 8-10, 3-21: an independent series (~1 mm)."""
    e2 = f * (2 - f)
    ep2 = e2 / (1 - e2)
    phi, lam = np.radians(lat), np.radians(lon - lon0)
    N = a / np.sqrt(1 - e2 * np.sin(phi) ** 2)
    T, C, A = np.tan(phi) ** 2, ep2 * np.cos(phi) ** 2, lam * np.cos(phi)
    M = a * ((1 - e2 / 4 - 3 * e2**2 / 64 - 5 * e2**3 / 256) * phi
             - (3 * e2 / 8 + 3 * e2**2 / 32 + 45 * e2**3 / 1024) * np.sin(2 * phi)
             + (15 * e2**2 / 256 + 45 * e2**3 / 1024) * np.sin(4 * phi)
             - (35 * e2**3 / 3072) * np.sin(6 * phi))
    x = k0 * N * (A + (1 - T + C) * A**3 / 6 + (5 - 18 * T + T**2 + 72 * C - 58 * ep2) * A**5 / 120)
    y = k0 * (M + N * np.tan(phi) * (A**2 / 2 + (5 - T + 9 * C + 4 * C**2) * A**4 / 24
                                     + (61 - 58 * T + T**2 + 600 * C - 330 * ep2) * A**6 / 720))
    return x, y


def test_snyder_published_example_clarke1866():
    # Snyder, Map Projections - A Working Manual, p. 269: x = 127,106.5 m, y = 4,484,124.4 m.
    clarke = gps.Ellipsoid(6378206.4, 1 - math.sqrt(1 - 0.00676866))
    x, y = gps.transverse_mercator(40.5, -73.5, lon0=-75.0, k0=0.9996, ellipsoid=clarke)
    assert abs(x - 127106.5) < 0.06 and abs(y - 4484124.4) < 0.06


def test_epsg_guidance_note_example_british_national_grid():
    # EPSG Guidance Note 7-2, Transverse Mercator example (OSGB36 / British National Grid):
    # 50 30' N, 0 30' E -> E 577274.99 m, N 69740.50 m (their USGS-series formula, ~cm).
    airy = gps.Ellipsoid(6377563.396, 1 / 299.3249646)
    E, N = gps.transverse_mercator(50.5, 0.5, lon0=-2.0, k0=0.9996012717, lat0=49.0,
                                   false_easting=400000.0, false_northing=-100000.0,
                                   ellipsoid=airy)
    assert abs(E - 577274.99) < 0.02 and abs(N - 69740.50) < 0.02


def test_against_independent_snyder_series_and_round_trip():
    rng = np.random.default_rng(0)
    lat = rng.uniform(-80, 84, 3000)
    zone = rng.integers(1, 61, 3000)
    lon = 6.0 * zone - 183.0 + rng.uniform(-3, 3, 3000)
    lon = (lon + 180) % 360 - 180
    for z in (5, 33, 60):
        sel = zone == z
        E, N, _, _ = gps.latlon_to_utm(lat[sel], lon[sel], zone=z, north=True)
        x, y = _snyder_tm(lat[sel], lon[sel], 6.0 * z - 183.0)
        np.testing.assert_allclose(E, 500000.0 + x, atol=2e-3)
        np.testing.assert_allclose(N, y, atol=2e-3)
        la, lo = gps.utm_to_latlon(E, N, z, True)
        np.testing.assert_allclose(la, lat[sel], atol=1e-10)
        np.testing.assert_allclose((lo - lon[sel] + 180) % 360 - 180, 0.0, atol=1e-10)
    E, N, z, north = gps.latlon_to_utm(-33.8568, 151.2153)  # Sydney: zone 56 South
    assert z == 56 and not north and 300000 < E < 400000 and 6.2e6 < N < 6.3e6


def test_zones():
    assert gps.utm_zone(34.2, -118.17) == 11     # Arroyo Seco, Pasadena
    assert gps.utm_zone(0.0, -180.0) == 1 and gps.utm_zone(0.0, 179.99) == 60
    assert gps.utm_zone(0.0, 0.0) == 31 and gps.utm_zone(0.0, -0.01) == 30
    assert gps.utm_zone(60.0, 5.0) == 32         # Norway exception
    assert gps.utm_zone(78.0, 10.0) == 33 and gps.utm_zone(78.0, 8.9) == 31  # Svalbard
    assert gps.utm_epsg(11, True) == 32611 and gps.utm_epsg(56, False) == 32756


def test_against_pyproj_if_installed():
    pyproj = pytest.importorskip("pyproj")
    rng = np.random.default_rng(1)
    for la, lo in zip(rng.uniform(-80, 84, 200), rng.uniform(-180, 180, 200)):
        E, N, z, north = gps.latlon_to_utm(la, lo)
        ref = pyproj.Transformer.from_crs(4326, gps.utm_epsg(z, north), always_xy=True)
        e2, n2 = ref.transform(lo, la)
        assert abs(E - e2) < 1e-6 and abs(N - n2) < 1e-6


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "gps.csv"
    p.write_text(text)
    return p


def test_reader_header_aliases_comments_and_skips(tmp_path):
    p = _write(tmp_path, "# WAAS log\n"
                         "Timestamp, Latitude, Longitude, HDOP, EPE\n"
                         "10.0, 34.2000, -118.1700, 1.1, 4.0\n"
                         "11.0, 34.2001, -118.1700, 1.1, nan\n"       # EPE NaN: skipped
                         "12.0, nan, -118.1700, 1.1, 5.0   # lost fix\n"  # skipped
                         "13.0, 34.2002, -118.1701, 1.1, 0\n"         # EPE 0: skipped
                         "14.0, 34.2003, -118.1702, 1.2, 6.5\n")
    log = gps.read_gps_log(p)
    assert log.n_skipped == 3 and log.time.tolist() == [10.0, 14.0]
    assert log.zone == 11 and log.north and log.epsg == 32611
    np.testing.assert_allclose(log.epe, [4.0, 6.5])
    E, N, _, _ = gps.latlon_to_utm(log.lat, log.lon, zone=11)
    np.testing.assert_allclose(log.xy + log.origin, np.stack([E, N], -1), atol=1e-9)
    assert np.all(log.origin % 100 == 0) and np.all(np.abs(log.xy) < 100)
    # 3e-4 deg of latitude (~33 m) and 2e-4 deg of longitude (~18 m) apart.
    assert 30 < np.hypot(*(log.xy[1] - log.xy[0])) < 40
    with pytest.raises(gps.GpsLogError, match=r"gps.csv:4: EPE must be positive"):
        gps.read_gps_log(p, strict=True)


def test_reader_without_header_whitespace(tmp_path):
    p = _write(tmp_path, "0 34.2 -118.17 3.5\n1 34.2001 -118.17 3.5\n2 34.2002 -118.17 3.5\n")
    log = gps.read_gps_log(p, origin=(394000.0, 3783000.0))
    assert log.n_skipped == 0 and log.xy.shape == (3, 2)
    np.testing.assert_array_equal(log.origin, [394000.0, 3783000.0])


@pytest.mark.parametrize("text,pattern", [
    ("time,lat,lon\n0,34,-118\n", r"gps.csv:1: header has no 'epe' column"),
    ("0,34.2,-118.17,3\n1,34.2,-118.17\n", r"gps.csv:2: expected at least 4 fields"),
    ("0,34.2,-118.17,3\n1,34.2,abc,3\n", r"gps.csv:2: not a number"),
    ("5,34.2,-118.17,3\n4,34.2,-118.17,3\n", r"gps.csv:2: time 4.0 goes backwards"),
    ("0,34.2,-118.17,3\n1,34.2,-118.17,-2\n", r"gps.csv: need at least 2 usable GPS readings, "
                                              r"found 1 \(1 skipped\)"),
    ("", r"need at least 2 usable"),
])
def test_reader_errors_name_file_and_line(tmp_path, text, pattern):
    with pytest.raises(gps.GpsLogError, match=pattern):
        gps.read_gps_log(_write(tmp_path, text))


def test_reader_missing_file(tmp_path):
    with pytest.raises(gps.GpsLogError, match="nope.csv: cannot read"):
        gps.read_gps_log(tmp_path / "nope.csv")


@pytest.mark.parametrize("text,pattern", [
    # lat and lon swapped: the first reading names the line and asks
    ("time,lat,lon,epe\n0,-118.17,34.2,3\n1,-118.17,34.2,3\n",
     r"gps.csv:2: latitude -118.17 is out of range \(-90 to 90\); are latitude and longitude "
     r"swapped\? \(the columns are time, lat, lon, epe\)"),
    ("0,34.2,-118.17,3\n1,34.2,-118.17,3\n2,95.5,200.0,3\n",
     r"gps.csv:3: latitude 95.5 is out of range \(-90 to 90\)$"),
    ("0,34.2,-118.17,3\n1,34.2,-400.0,3\n", r"gps.csv:2: longitude -400.0 is out of range"),
    # every reading skipped: the count and the first one's reason
    ("0,nan,-118.17,3\n1,34.2,-118.17,0\n", r"found 0 \(2 skipped\); the first skipped, line 1: "
                                            r"non-finite coordinate"),
])
def test_reader_names_out_of_range_coordinates_and_why_readings_were_skipped(tmp_path, text,
                                                                             pattern):
    with pytest.raises(gps.GpsLogError, match=pattern):
        gps.read_gps_log(_write(tmp_path, text))


def test_reader_keeps_each_readings_line(tmp_path):
    p = _write(tmp_path, "time,lat,lon,epe\n# comment\n0,34.2,-118.17,3\n1,nan,-118.17,3\n\n"
                         "2,34.2001,-118.17,3\n")
    assert gps.read_gps_log(p).lines.tolist() == [3, 6]
