"""The georeferenced map as a GeoTIFF in its UTM CRS (optional extra ``geotiff``: rasterio).

A run with ``--gps`` writes ``map_utm.png`` with a world file (``gps.raster``); beside it,
``map_utm.tif`` holds the same north-up raster as numbers a GIS reads with its CRS (EPSG 326NN
north, 327NN south, from the GPS log's zone and hemisphere): band 1 the expected std of the
heights (metres), band 2 the cell's degrees of freedom ``k`` (the heights observed, less one per
local map, times ``[map] obs_weight``), float32, ``NODATA`` where no height was observed. The
affine transform is the world file's (the SLAM map rotated into UTM by the GPS alignment), moved
from the top-left pixel's centre to its corner: the raster is the map's own lattice, turned
into UTM, so the transform has rotation terms that web and tile viewers do not read.

Beside it, ``map_utm_north.tif`` holds the map resampled onto a north-up UTM grid of the map's
cell size (:func:`north_up`: each pixel takes the value of the map cell its centre falls in,
nearest neighbour, so every value is a value of the map; NODATA outside the map and where it
is unobserved): a transform without rotation terms. Without rasterio the run still succeeds and
says once why no GeoTIFF was written.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["GEOTIFF_NAME", "NORTH_UP_NAME", "NODATA", "BANDS", "INSTALL_HINT", "NorthUp",
           "geotiff_transform", "north_up", "run_north_up", "write_map_geotiff",
           "write_north_up_geotiff", "write_run_geotiff"]

GEOTIFF_NAME = "map_utm.tif"
NORTH_UP_NAME = "map_utm_north.tif"
NODATA = -9999.0
BANDS = ("expected_std_m", "k")  # band descriptions, in order
INSTALL_HINT = "pip install 'gslam-jax[geotiff]' (rasterio)"


def geotiff_transform(world_params: ArrayLike) -> tuple[float, ...]:
    """The GDAL/rasterio affine (a, b, c, d, e, f) of the world-file numbers (A, D, B, E, C,
    F): X = a col + b row + c with (col, row) at the pixel's corner, so (c, f) is the top-left
    pixel's outer corner, half a pixel from the world file's centre."""
    A, D, B, E, C, F = (float(v) for v in np.asarray(world_params, np.float64))
    return (A, B, C - 0.5 * (A + B), D, E, F - 0.5 * (D + E))


def write_map_geotiff(path: str | Path, std: ArrayLike, k: ArrayLike,
                      map_origin: tuple[float, float], resolution: float, R: ArrayLike,
                      shift: ArrayLike, site_origin: ArrayLike, epsg: int) -> Path:
    """Write the map (expected std and k, each [nx, ny] with axis 0 = SLAM x) as a two-band
    float32 GeoTIFF in EPSG ``epsg``, placed by the GPS alignment (R, l = ``shift``) and the
    site origin as the world file of ``gps.write_georeferenced_png`` places the PNG. Cells
    with k = 0 or a non-finite std are NODATA. ImportError without rasterio."""
    import rasterio
    from rasterio.crs import CRS
    from rasterio.transform import Affine

    from gslam_jax.gps.raster import world_file_params

    path = Path(path)
    std = np.asarray(std, np.float64)
    k = np.asarray(k, np.float64)
    if std.shape != k.shape or std.ndim != 2:
        raise ValueError(f"std and k must be 2-D arrays of one shape, got {std.shape} and "
                         f"{k.shape}")
    known = (k > 0) & np.isfinite(std)
    bands = np.stack([np.where(known, std, NODATA), np.where(known, k, NODATA)])
    bands = np.flip(np.swapaxes(bands, 1, 2), axis=1).astype(np.float32)  # north-up rows
    params = world_file_params(map_origin, resolution, std.shape, R, shift, site_origin)
    profile = {"driver": "GTiff", "width": std.shape[0], "height": std.shape[1],
               "count": len(BANDS), "dtype": "float32", "nodata": NODATA,
               "crs": CRS.from_epsg(int(epsg)), "transform": Affine(*geotiff_transform(params)),
               "compress": "deflate"}
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(bands)
        for i, name in enumerate(BANDS, start=1):
            dst.set_band_description(i, name)
        dst.update_tags(source="gslam-jax", map="the best particle's variance grid map",
                        expected_std_m="posterior expected std of the cell's point heights (m)",
                        k="degrees of freedom: heights observed, less one per local map")
    return path


class NorthUp(NamedTuple):
    """A map resampled onto a north-up UTM grid (:func:`north_up`)."""

    bands: np.ndarray                       # [len(BANDS), rows, cols] float32, NODATA outside
    transform: tuple[float, ...]            # GDAL affine (a, 0, c, 0, e, f): (c, f) top-left
    epsg: int                               # corner, a = -e = the cell size


def north_up(std: ArrayLike, k: ArrayLike, map_origin: tuple[float, float], resolution: float,
             R: ArrayLike, shift: ArrayLike, site_origin: ArrayLike, epsg: int) -> NorthUp:
    """The map (expected std and k, [nx, ny] on its lattice's axes from ``map_origin``) on a
    north-up grid of ``resolution`` metres covering its observed cells: a pixel centre at UTM
    (E, N) lies at lattice point R^T ((E, N) - shift - site_origin), and takes the value of
    the cell that point falls in (NODATA outside the map, or where k = 0 or the std is not
    finite). ``R``: the GPS alignment's rotation of the lattice (``lattice_rotation``)."""
    std = np.asarray(std, np.float64)
    k = np.asarray(k, np.float64)
    if std.shape != k.shape or std.ndim != 2:
        raise ValueError(f"std and k must be 2-D arrays of one shape, got {std.shape} and "
                         f"{k.shape}")
    R = np.asarray(R, np.float64)
    offset = np.asarray(shift, np.float64) + np.asarray(site_origin, np.float64)
    res = float(resolution)
    known = (k > 0) & np.isfinite(std)
    i, j = np.nonzero(known) if known.any() else np.nonzero(np.ones_like(known))
    x0, y0 = float(map_origin[0]), float(map_origin[1])
    corners = np.array([[x0 + i.min() * res, y0 + j.min() * res],
                        [x0 + (i.max() + 1) * res, y0 + j.min() * res],
                        [x0 + (i.max() + 1) * res, y0 + (j.max() + 1) * res],
                        [x0 + i.min() * res, y0 + (j.max() + 1) * res]]) @ R.T + offset
    west, south = np.floor(corners.min(axis=0) / res) * res
    east, north = np.ceil(corners.max(axis=0) / res) * res
    cols, rows = int(round((east - west) / res)), int(round((north - south) / res))
    E = west + (np.arange(cols) + 0.5) * res
    N = north - (np.arange(rows) + 0.5) * res
    EE, NN = np.meshgrid(E, N)  # [rows, cols]
    local = np.stack([EE - offset[0], NN - offset[1]], -1) @ R  # R^T applied to each point
    ci = np.floor((local[..., 0] - x0) / res).astype(np.int64)
    cj = np.floor((local[..., 1] - y0) / res).astype(np.int64)
    inside = (ci >= 0) & (ci < std.shape[0]) & (cj >= 0) & (cj < std.shape[1])
    ci, cj = np.where(inside, ci, 0), np.where(inside, cj, 0)
    ok = inside & known[ci, cj]
    bands = np.stack([np.where(ok, std[ci, cj], NODATA), np.where(ok, k[ci, cj], NODATA)])
    return NorthUp(bands.astype(np.float32), (res, 0.0, float(west), 0.0, -res, float(north)),
                   int(epsg))


def write_north_up_geotiff(path: str | Path, grid: NorthUp) -> Path:
    """Write a :class:`NorthUp` map as a two-band float32 GeoTIFF. ImportError without
    rasterio."""
    import rasterio
    from rasterio.crs import CRS
    from rasterio.transform import Affine

    path = Path(path)
    profile = {"driver": "GTiff", "width": grid.bands.shape[2], "height": grid.bands.shape[1],
               "count": len(BANDS), "dtype": "float32", "nodata": NODATA,
               "crs": CRS.from_epsg(grid.epsg), "transform": Affine(*grid.transform),
               "compress": "deflate"}
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(grid.bands)
        for i, name in enumerate(BANDS, start=1):
            dst.set_band_description(i, name)
        dst.update_tags(source="gslam-jax", map="the best particle's variance grid map, "
                        "resampled north-up (nearest cell)",
                        expected_std_m="posterior expected std of the cell's point heights (m)",
                        k="degrees of freedom: heights observed, less one per local map")
    return path


def run_north_up(out: Path, std: ArrayLike, k: ArrayLike, map_origin: tuple[float, float],
                 resolution: float, heading: float = 0.0) -> NorthUp:
    """:func:`north_up` of a run's map, placed by the ``gps_alignment.npz`` in ``out``."""
    from gslam_jax.gps.raster import lattice_rotation

    with np.load(out / "gps_alignment.npz") as al:
        R, shift, site, epsg = (np.asarray(al[f]) for f in ("R", "l", "site_origin", "epsg"))
    return north_up(std, k, map_origin, resolution, lattice_rotation(R, heading), shift, site,
                    int(epsg))


def write_run_geotiff(out: Path, std: ArrayLike, k: ArrayLike,
                      map_origin: tuple[float, float], resolution: float,
                      heading: float = 0.0) -> dict:
    """``map_utm.tif`` in the results folder ``out``, placed by the ``gps_alignment.npz``
    written there (``georeference.write_gps_outputs``; a lattice turned by ``heading`` in the
    run's frame, ``GridMap.heading``, turned with it); the summary's figures: the file's
    name and the north-up one's (``NORTH_UP_NAME``), or None and a note when rasterio is
    missing (printed, the run goes on)."""
    try:
        import rasterio  # noqa: F401 - only to know whether the GeoTIFF can be written
    except ImportError:
        note = (f"no {GEOTIFF_NAME} or {NORTH_UP_NAME} (GeoTIFF): rasterio is not installed; "
                f"{INSTALL_HINT}")
        print(f"note: {note}")
        return {"geotiff": None, "geotiff_north_up": None, "geotiff_note": note}
    from gslam_jax.gps.raster import lattice_rotation

    with np.load(out / "gps_alignment.npz") as al:
        R, shift, site, epsg = (np.asarray(al[f]) for f in ("R", "l", "site_origin", "epsg"))
    R = lattice_rotation(R, heading)
    write_map_geotiff(out / GEOTIFF_NAME, std, k, map_origin, resolution, R, shift, site,
                      int(epsg))
    write_north_up_geotiff(out / NORTH_UP_NAME, north_up(std, k, map_origin, resolution, R,
                                                         shift, site, int(epsg)))
    return {"geotiff": GEOTIFF_NAME, "geotiff_north_up": NORTH_UP_NAME}
