"""The map in the formats robotics and GIS users open (issue 68, "Figures and formats"): a
north-up GeoTIFF beside the rotated one, checked with rasterio against the rotated file; the
georeferenced map as a figure; the occupancy grid for ROS map_server (PGM + YAML), parsed as
map_server reads it and checked against map.npz by hand."""

from __future__ import annotations

import json

import numpy as np
import pytest
from synthetic import make_run
from reference_maps import expected_std

from gslam_jax.app import occupancy, plots
from gslam_jax.app.cli import main
from gslam_jax.run import save_run


@pytest.fixture(scope="module")
def gps_run(tmp_path_factory):
    run, _ = make_run(steps=20)
    folder = tmp_path_factory.mktemp("exports")
    save_run(folder / "r.npz", run)
    out = folder / "out"
    assert main(["run", str(folder / "r.npz"), "--set", "filter.particles=8", "--gps", "sim",
                 "--out", str(out)]) == 0
    return out


# -- north-up GeoTIFF -------------------------------------------------------------------------

def test_north_up_geotiff_has_no_rotation_and_the_rotated_files_values(gps_run):
    rasterio = pytest.importorskip("rasterio")
    with np.load(gps_run / "map.npz") as m:
        res = float(m["resolution"])
        known_cells = int((m["k"] > 0).sum())
    with rasterio.open(gps_run / "map_utm.tif") as rot, \
            rasterio.open(gps_run / "map_utm_north.tif") as north:
        t = north.transform
        assert rot.transform.b != 0 or rot.transform.d != 0  # the rotated one is rotated
        assert t.b == 0 and t.d == 0 and t.a == pytest.approx(res) and t.e == pytest.approx(-res)
        assert north.nodata == -9999.0 and north.crs == rot.crs
        assert north.descriptions == ("expected_std_m", "k")
        n_std, n_k = north.read(1), north.read(2)
        r_std, r_k = rot.read(1), rot.read(2)
        data = np.argwhere(n_std != north.nodata)
        assert len(data) > 0.5 * known_cells
        rng = np.random.default_rng(0)
        for row, col in rng.choice(data, 200, replace=False):
            # the pixel's centre, located in the rotated file by its own (rotated) transform
            rr, rc = rot.index(*north.xy(row, col))
            assert n_std[row, col] == r_std[rr, rc] and n_k[row, col] == r_k[rr, rc]
        for row, col in rng.choice(np.argwhere(n_std == north.nodata), 200, replace=False):
            rr, rc = rot.index(*north.xy(row, col))
            outside = not (0 <= rr < rot.height and 0 <= rc < rot.width)
            assert outside or r_std[rr, rc] == rot.nodata
    gps = json.loads((gps_run / "summary.json").read_text())["gps"]
    assert gps["geotiff_north_up"] == "map_utm_north.tif"


def test_utm_map_is_a_figure(gps_run, monkeypatch):
    from matplotlib.image import imread

    img = imread(gps_run / "map_utm_figure.png")[..., :3]
    assert np.mean(img.max(axis=-1) < 0.1) < 0.3  # not almost all black
    kept = []
    monkeypatch.setattr(plots.plt, "close", lambda fig=None: kept.append(fig))
    std = np.full((40, 60), np.nan)
    std[5:30, 10:50] = 0.05
    plots.save_utm_map_png(gps_run.parent / "f.png", std,
                           (0.16, 0.0, 389_123.0, 0.0, -0.16, 3_777_456.0),
                           np.array([[389_125.0, 3_777_452.0], [389_130.0, 3_777_451.0]]),
                           crs="EPSG:32611")
    (fig,) = kept
    ax = next(a for a in fig.axes if a.get_images())
    assert "EPSG:32611" in ax.get_title()
    assert ax.get_xlabel() == "easting - 389,100 (m)"
    assert ax.get_ylabel() == "northing - 3,777,400 (m)"
    assert len(fig.axes) == 2  # the map and its colour bar
    assert ax.get_legend() is not None
    plots.plt.close(fig)


def test_north_up_by_brute_force():
    from gslam_jax.app.geotiff import NODATA, north_up

    rng = np.random.default_rng(3)
    std = rng.uniform(0.01, 1.0, (30, 20))
    k = rng.integers(0, 5, (30, 20)).astype(float)
    th = 0.7
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    grid = north_up(std, k, (-2.0, 1.0), 0.2, R, [3.0, -4.0], [500_000.0, 4_000_000.0], 32633)
    a, _, c, _, e, f = grid.transform
    rows, cols = grid.bands.shape[1:]
    for row in range(0, rows, 3):
        for col in range(0, cols, 3):
            E, N = c + (col + 0.5) * a, f + (row + 0.5) * e
            x, y = np.linalg.solve(R, np.array([E, N]) - [3.0, -4.0] - [500_000.0, 4_000_000.0])
            i, j = int(np.floor((x + 2.0) / 0.2)), int(np.floor((y - 1.0) / 0.2))
            if 0 <= i < 30 and 0 <= j < 20 and k[i, j] > 0:
                assert grid.bands[0, row, col] == np.float32(std[i, j])
            else:
                assert grid.bands[0, row, col] == NODATA


# -- occupancy grid for map_server ------------------------------------------------------------

def _read_pgm(path):
    """A binary PGM's (width, height, maxval, pixels [height, width]), read by hand."""
    data = path.read_bytes()
    fields, pos = [], 0
    while len(fields) < 4:
        while data[pos:pos + 1].isspace():
            pos += 1
        if data[pos:pos + 1] == b"#":
            pos = data.index(b"\n", pos) + 1
            continue
        end = pos
        while not data[end:end + 1].isspace():
            end += 1
        fields.append(data[pos:end].decode())
        pos = end
    magic, width, height, maxval = fields[0], int(fields[1]), int(fields[2]), int(fields[3])
    assert magic == "P5"
    pixels = np.frombuffer(data[pos + 1:], np.uint8)
    assert pixels.size == width * height
    return width, height, maxval, pixels.reshape(height, width)


def _map_server_reading(pixels, meta):
    """What map_server makes of each pixel (trinary, negate 0): 100 occupied, 0 free, -1
    unknown."""
    p = (255.0 - pixels) / 255.0
    return np.where(p > meta["occupied_thresh"], 100, np.where(p < meta["free_thresh"], 0, -1))


def test_occupancy_files_parse_and_known_cells_land_right(tmp_path):
    yaml = pytest.importorskip("yaml")
    std = np.full((6, 4), 0.02)       # flat ground
    std[1, 2] = 0.5                   # a rock at x cell 1, y cell 2
    std[4, 0] = np.nan                # never observed
    std[5, 3] = occupancy.ROUGH_STD_M  # at the threshold: free
    pgm, meta_file = occupancy.write_occupancy(tmp_path, std, (-1.0, 2.0, 0.25), 0.16)
    meta = yaml.safe_load(meta_file.read_text())
    assert meta["image"] == pgm.name and meta["resolution"] == 0.16
    assert meta["origin"] == [-1.0, 2.0, 0.25] and meta["negate"] == 0
    assert 0 < meta["free_thresh"] < meta["occupied_thresh"] < 1
    width, height, maxval, pixels = _read_pgm(pgm)
    assert (width, height, maxval) == (6, 4, 255)
    reading = _map_server_reading(pixels, meta)
    # row 0 of the image is the top (largest y): cell (i, j) is pixel (height - 1 - j, i)
    assert reading[4 - 1 - 2, 1] == 100
    assert reading[4 - 1 - 0, 4] == -1
    assert reading[4 - 1 - 3, 5] == 0
    assert (reading == 0).sum() == 6 * 4 - 2


def test_a_runs_occupancy_grid_is_its_map(gps_run):
    yaml = pytest.importorskip("yaml")
    with np.load(gps_run / "map.npz") as m:
        k, S = m["k"].astype(np.float64), m["S"].astype(np.float64)
        (x0, y0), res = m["origin"], float(m["resolution"])
    meta = yaml.safe_load((gps_run / "map_occupancy.yaml").read_text())
    assert meta["resolution"] == pytest.approx(res)
    assert meta["origin"][:2] == pytest.approx([x0, y0])
    width, height, _, pixels = _read_pgm(gps_run / "map_occupancy.pgm")
    assert (width, height) == k.shape
    std = expected_std(k, S)
    # the float32 map's std against float64 here: cells within rounding of the threshold aside
    clear = ~np.isfinite(std) | (np.abs(std - occupancy.ROUGH_STD_M) > 1e-5)
    want = np.where(np.isnan(std), -1, np.where(std > occupancy.ROUGH_STD_M, 100, 0))
    got = _map_server_reading(pixels, meta)[::-1].T  # back to [nx, ny] cells
    np.testing.assert_array_equal(got[clear], want[clear])
    assert (want == 100).any() and (want == 0).any() and (want == -1).any()
