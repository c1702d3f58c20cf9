"""Georeferenced rasters: a SLAM map as a north-up PNG with a world file that places it in UTM.

The map stays in the SLAM frame; the GPS alignment (R, l) and the site origin give the six
world-file numbers, which GIS tools read beside the PNG (``.pgw``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from jax.typing import ArrayLike

__all__ = ["map_corners", "lattice_rotation", "world_file_params", "write_world_file",
           "write_georeferenced_png"]


def map_corners(map_origin: tuple[float, float], resolution: float,
                map_shape: tuple[int, int]) -> np.ndarray:
    """SLAM-frame corners [4,2] of a map whose cell (i, j) covers x0 + i res, y0 + j res
    (FilterConfig convention), counter-clockwise from (x0, y0)."""
    x0, y0 = map_origin
    w, h = map_shape[0] * resolution, map_shape[1] * resolution
    return np.array([[x0, y0], [x0 + w, y0], [x0 + w, y0 + h], [x0, y0 + h]], np.float64)


def lattice_rotation(R: ArrayLike, heading: float) -> np.ndarray:
    """The GPS alignment's rotation ``R`` (SLAM frame -> site frame) of a map whose lattice lies
    at ``heading`` radians in the SLAM frame (``GridMap.heading``): R R(heading), which takes
    the lattice's axes to the site frame (``map_corners`` and ``world_file_params`` read the
    map on them)."""
    c, s = np.cos(heading), np.sin(heading)
    return np.asarray(R, np.float64) @ np.array([[c, -s], [s, c]])


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
