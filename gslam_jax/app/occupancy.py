"""The map as an occupancy grid for ROS ``map_server`` (and nav2, GMapping's users): a PGM image
and its YAML description.

A variance map has no occupancy; it has how rough each cell is. A cell whose expected std of
heights (``rbpf.cells.expected_std``) exceeds ``ROUGH_STD_M`` is written occupied (rough or
tall: rocks, walls, vegetation), one at or below it free (flat ground), an unobserved cell
unknown. The PGM holds ``map_server``'s trinary values with ``negate: 0``: 0 (black, occupied),
254 (white, free) and 205 (grey, unknown), row 0 the map's top (largest y) as ``map_server``
reads it; the YAML's ``origin`` is the pose of the lower-left pixel's corner, ``[x, y, yaw]`` in
the run's frame (yaw: the lattice's heading, ``GridMap.heading``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

__all__ = ["ROUGH_STD_M", "OCCUPIED", "FREE", "UNKNOWN", "OCCUPIED_THRESH", "FREE_THRESH",
           "PGM_NAME", "YAML_NAME", "occupancy_image", "write_occupancy"]

ROUGH_STD_M = 0.1     # metres of expected std: above it a cell is occupied
OCCUPIED, FREE, UNKNOWN = 0, 254, 205
# map_server reads a pixel v (negate: 0) as occupancy p = (255 - v) / 255: 0 -> 1.0 (occupied),
# 254 -> 0.004 (free), 205 -> 0.196 (between the thresholds: unknown)
OCCUPIED_THRESH = 0.65
FREE_THRESH = 0.196
PGM_NAME = "map_occupancy.pgm"
YAML_NAME = "map_occupancy.yaml"


def occupancy_image(std: np.ndarray, rough_std: float = ROUGH_STD_M) -> np.ndarray:
    """The PGM's pixels (uint8 [ny, nx], row 0 the largest y) of an expected-std map
    ``std`` [nx, ny] (axis 0 is x, NaN = unobserved)."""
    std = np.asarray(std, np.float64)
    if std.ndim != 2:
        raise ValueError(f"std must be a 2-D [Nx, Ny] array, got shape {std.shape}")
    if not rough_std > 0:
        raise ValueError(f"rough_std must be positive, got {rough_std}")
    pixels = np.full(std.shape, UNKNOWN, np.uint8)
    known = np.isfinite(std)
    pixels[known & (std > rough_std)] = OCCUPIED
    pixels[known & (std <= rough_std)] = FREE
    return np.ascontiguousarray(np.flipud(pixels.T))


def write_occupancy(folder: str | Path, std: np.ndarray, origin: Sequence[float],
                    resolution: float, rough_std: float = ROUGH_STD_M) -> tuple[Path, Path]:
    """Write ``PGM_NAME`` (binary P5) and ``YAML_NAME`` into ``folder`` for the map ``std``
    [nx, ny] whose cell (0, 0)'s corner is ``origin`` (x, y) or (x, y, heading), cells
    ``resolution`` metres; returns both paths."""
    folder = Path(folder)
    pixels = occupancy_image(std, rough_std)
    x0, y0 = float(origin[0]), float(origin[1])
    yaw = float(origin[2]) if len(origin) == 3 else 0.0
    pgm, yaml = folder / PGM_NAME, folder / YAML_NAME
    rows, cols = pixels.shape
    pgm.write_bytes(f"P5\n# gslam-jax: expected std > {rough_std:g} m occupied\n"
                    f"{cols} {rows}\n255\n".encode("ascii") + pixels.tobytes())
    yaml.write_text(
        f"# gslam-jax map for ROS map_server: a cell is occupied when the expected std of its\n"
        f"# heights exceeds {rough_std:g} m (rough or tall), free at or below it, unknown when\n"
        f"# unobserved; origin: the lower-left pixel's corner [x, y, yaw] in the run's frame\n"
        f"image: {PGM_NAME}\n"
        f"mode: trinary\n"
        f"resolution: {float(resolution)!r}\n"
        f"origin: [{x0!r}, {y0!r}, {yaw!r}]\n"
        f"negate: 0\n"
        f"occupied_thresh: {OCCUPIED_THRESH}\n"
        f"free_thresh: {FREE_THRESH}\n")
    return pgm, yaml
