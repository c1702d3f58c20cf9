"""The georeferenced map as a GeoTIFF in its UTM CRS (optional extra ``geotiff``: rasterio).

A run with ``--gps`` writes ``map_utm.png`` with a world file (``gps.raster``); beside it,
``map_utm.tif`` holds the same north-up raster as numbers a GIS reads with its CRS (EPSG 326NN
north, 327NN south, from the GPS log's zone and hemisphere): band 1 the expected std of the
heights (metres), band 2 the cell's degrees of freedom ``k`` (the heights observed, less one per
local map, times ``[map] obs_weight``), float32, ``NODATA`` where no height was observed. The
affine transform is the world file's (the SLAM map rotated into UTM by the GPS alignment), moved
from the top-left pixel's centre to its corner. Without rasterio the run still succeeds and
says once why no GeoTIFF was written.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["GEOTIFF_NAME", "NODATA", "BANDS", "INSTALL_HINT", "geotiff_transform",
           "write_map_geotiff", "write_run_geotiff"]

GEOTIFF_NAME = "map_utm.tif"
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


def write_run_geotiff(out: Path, std: ArrayLike, k: ArrayLike,
                      map_origin: tuple[float, float], resolution: float,
                      heading: float = 0.0) -> dict:
    """``map_utm.tif`` in the results folder ``out``, placed by the ``gps_alignment.npz``
    written there (``georeference.write_gps_outputs``; a lattice turned by ``heading`` in the
    run's frame, ``GridMap.heading``, turned with it); the summary's figures: the file's
    name, or None and a note when rasterio is missing (printed, the run goes on)."""
    try:
        import rasterio  # noqa: F401 - only to know whether the GeoTIFF can be written
    except ImportError:
        note = f"no {GEOTIFF_NAME} (GeoTIFF): rasterio is not installed; {INSTALL_HINT}"
        print(f"note: {note}")
        return {"geotiff": None, "geotiff_note": note}
    from gslam_jax.gps.raster import lattice_rotation

    with np.load(out / "gps_alignment.npz") as al:
        R, shift, site, epsg = (np.asarray(al[f]) for f in ("R", "l", "site_origin", "epsg"))
    write_map_geotiff(out / GEOTIFF_NAME, std, k, map_origin, resolution,
                      lattice_rotation(R, heading), shift, site, int(epsg))
    return {"geotiff": GEOTIFF_NAME}
