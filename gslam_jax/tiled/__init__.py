"""Tiled copy-on-write reference implementation of the Gamma-SLAM filter (paper 6.3).

An independent NumPy filter with the paper's map storage, driven by the same random numbers as
the dense JAX filter; ``compare`` checks that the two agree and sets their time and memory side
by side.
"""

from gslam_jax.tiled.reference import (DEFAULT_TILE_SIZE, TiledOutput, TiledState, init,
                                       memory_snapshot, predict, run_tiled, update)
from gslam_jax.tiled.tiles import Ledger, Tile, TileMap, tile_cells

__all__ = ["DEFAULT_TILE_SIZE", "TiledOutput", "TiledState", "init", "memory_snapshot", "predict",
           "run_tiled", "update", "Ledger", "Tile", "TileMap", "tile_cells"]
