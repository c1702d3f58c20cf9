"""``map_utm.tif``: a ``--gps sim`` run's map as a GeoTIFF, opened with rasterio and checked
against ``gps_alignment.npz`` and ``map.npz`` by hand: the corners recomputed from the
alignment's R, l and site origin, the EPSG from trajectory_utm.txt's header, the cell values
from (k, S) with SciPy's gammaln; and the run without rasterio."""

from __future__ import annotations

import json
import re
import sys

import numpy as np
import pytest
from synthetic import make_run
from reference_maps import expected_std

from gslam_jax.app.cli import main
from gslam_jax.app.geotiff import geotiff_transform
from gslam_jax.driver import slam
from gslam_jax.driver.results import PathEstimates, SlamResult
from gslam_jax.run import save_run


@pytest.fixture(scope="module")
def run_file(tmp_path_factory):
    run, _ = make_run(steps=20)
    path = tmp_path_factory.mktemp("geotiff") / "r.npz"
    save_run(path, run)
    return path


@pytest.fixture(scope="module")
def gps_run(run_file):
    out = run_file.parent / "out"
    assert main(["run", str(run_file), "--set", "filter.particles=8", "--gps", "sim",
                 "--out", str(out)]) == 0
    return out


def test_transform_and_crs_agree_with_gps_alignment(gps_run):
    rasterio = pytest.importorskip("rasterio")
    with np.load(gps_run / "gps_alignment.npz") as al:
        R, shift, site = (np.asarray(al[f], np.float64) for f in ("R", "l", "site_origin"))
        zone, epsg, corners_utm = int(al["zone"]), int(al["epsg"]), al["map_corners_utm"]
    with np.load(gps_run / "map.npz") as m:
        k, S = m["k"].astype(np.float64), m["S"].astype(np.float64)
        (x0, y0), res = m["origin"], float(m["resolution"])
    nx, ny = k.shape
    header = (gps_run / "trajectory_utm.txt").read_text().splitlines()[0]
    zone_txt, hemi, epsg_txt = re.search(r"UTM zone (\d+)([NS]), EPSG:(\d+)", header).groups()
    assert int(zone_txt) == zone and int(epsg_txt) == epsg
    assert epsg == (32600 if hemi == "N" else 32700) + zone

    with rasterio.open(gps_run / "map_utm.tif") as ds:
        assert ds.crs.to_epsg() == epsg
        assert (ds.width, ds.height, ds.count) == (nx, ny, 2)
        assert ds.dtypes == ("float32", "float32") and ds.nodata == -9999.0
        assert ds.descriptions == ("expected_std_m", "k")
        # raster corners (col, row) -> the SLAM map's corners carried into UTM by hand
        slam_corner = {(0, 0): (x0, y0 + ny * res), (nx, 0): (x0 + nx * res, y0 + ny * res),
                       (nx, ny): (x0 + nx * res, y0), (0, ny): (x0, y0)}
        for (col, row), xy in slam_corner.items():
            want = R @ np.asarray(xy) + shift + site
            np.testing.assert_allclose(ds.transform @ (col, row), want, atol=1e-6)
        # ... and they are the alignment file's corners (its order: ccw from (x0, y0))
        got = [ds.transform @ cr for cr in ((0, ny), (nx, ny), (nx, 0), (0, 0))]
        np.testing.assert_allclose(got, corners_utm, atol=1e-3)
        std_band, k_band = ds.read(1), ds.read(2)
        # a known cell's centre in UTM lands in the pixel holding that cell's values
        for i, j in np.argwhere(k > 1)[:: max(1, int((k > 1).sum()) // 25)]:
            centre = R @ np.array([x0 + (i + 0.5) * res, y0 + (j + 0.5) * res]) + shift + site
            row, col = ds.index(*centre)
            assert (row, col) == (ny - 1 - j, i)
    std = expected_std(k, S)
    want_std = np.where(k > 0, std, -9999.0)[:, ::-1].T
    np.testing.assert_allclose(std_band, want_std, rtol=1e-4)  # the map's std is float32
    np.testing.assert_array_equal(k_band, np.where(k > 0, k, -9999.0)[:, ::-1].T)
    assert (k == 0).any() and (k > 0).any()
    summary = json.loads((gps_run / "summary.json").read_text())
    assert summary["gps"]["geotiff"] == "map_utm.tif"


def test_geotiff_transform_moves_the_centre_to_the_corner():
    # world file of a map rotated by 90 degrees: +1 column = +0.5 north, +1 row = +0.5 east
    A, D, B, E, C, F = 0.0, 0.5, 0.5, 0.0, 100.0, 200.0
    a, b, c, d, e, f = geotiff_transform([A, D, B, E, C, F])
    assert (a, b, d, e) == (A, B, D, E)
    # the top-left pixel's centre (0.5, 0.5) maps to the world file's (C, F)
    assert (a * 0.5 + b * 0.5 + c, d * 0.5 + e * 0.5 + f) == (C, F)


def test_without_rasterio_the_run_succeeds_and_says_why(run_file, tmp_path, capsys,
                                                        monkeypatch):
    monkeypatch.setitem(sys.modules, "rasterio", None)  # import rasterio -> ImportError

    def fake(run, config, progress=None, **kwargs):  # the filter is not what is tested here
        T, vo = run.num_frames, run.vo_poses()
        return SlamResult(
            paths=PathEstimates.given(best=vo, map=vo, smoothed=vo), best_pose=vo,
            mean_pose=vo, vo_path=vo,
            ess=np.full(T, 8.0), resampled=np.zeros(T, bool),
            updated=np.asarray(run.obs_index) >= 0, log_lik=np.zeros(T), exponent=np.ones(T),
            kmap=np.ones((24, 24), np.float32), smap=np.ones((24, 24), np.float32),
            map_origin=(-2.0, -2.0), resolution=0.16, extent_violations=0,
            empty_observations=0, seconds=0.0, compile_seconds=0.0)
    monkeypatch.setattr(slam, "run_slam", fake)
    out = tmp_path / "out"
    assert main(["run", str(run_file), "--gps", "sim", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert printed.count("rasterio is not installed") == 1 and "gslam-jax[geotiff]" in printed
    assert not (out / "map_utm.tif").exists() and (out / "map_utm.png").exists()
    gps = json.loads((out / "summary.json").read_text())["gps"]
    assert gps["geotiff"] is None and "rasterio is not installed" in gps["geotiff_note"]
