"""A ``World`` stored as tiles, for terrain generated only near a path (``corridor``).

A long recorded path crosses a bounding box whose full raster would not fit in memory (400
pixels a square metre, 13-21 bytes each), though the robot only ever sees ``max_range`` metres
of it. ``TiledWorld`` keeps the raster as square tiles, aligned to multiples of the tile size in
world coordinates, for the tiles that come within ``half_width`` of the driven path, plus one
empty tile (slot 0) that every other tile of the grid points to. It answers the sensor like a
dense ``World`` (``flat_index``, ``ground_at``), so memory grows with the path's length, not
with its bounding box.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np

from gslam_jax.sim.world import World

__all__ = ["TiledWorld", "corridor_tiles", "densify"]


@dataclass
class TiledWorld(World):
    """A ``World`` stored as tiles: every layer is [slots, tile_px, tile_px], slot 0 the empty
    tile; ``tiles`` [TX, TY] (int32) names the slot of each tile of the grid, whose pixel
    (0, 0) lies at ``origin``. Pixel (i, j) of the grid is pixel (i % tile_px, j % tile_px) of
    tile (i // tile_px, j // tile_px). Layers a kind never uses (crowns outside the arroyo) are
    one empty tile broadcast to every slot."""

    tiles: np.ndarray
    tile_px: int
    _window: tuple = field(default=(), init=False, repr=False, compare=False)

    @property
    def shape(self) -> tuple[int, int]:
        """The grid's size in pixels (as a dense raster would have it)."""
        return (self.tiles.shape[0] * self.tile_px, self.tiles.shape[1] * self.tile_px)

    @property
    def slots(self) -> int:
        return int(self.ground.shape[0])

    @property
    def has_canopy(self) -> bool:
        return self.canopy_lo.strides[0] != 0 and bool(np.isfinite(self.canopy_lo).any())

    @property
    def nbytes(self) -> int:
        """Bytes held by the layers and the tile table (a broadcast layer counts one tile)."""
        layers = (self.ground, self.height, self.rough, self.canopy_lo, self.canopy_hi,
                  self.material)
        return int(self.tiles.nbytes + sum(a.nbytes if a.strides[0] else a[0].nbytes
                                           for a in layers))

    def flat_index(self, ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
        """Indices into the raveled tile layers of grid pixels (ix, iy) (off the grid: the
        nearest pixel on it; outside the corridor: the empty tile)."""
        b = self.tile_px
        shift = b.bit_length() - 1
        ix = np.clip(ix, 0, self.shape[0] - 1)
        iy = np.clip(iy, 0, self.shape[1] - 1)
        slot = self.tiles[ix >> shift, iy >> shift]
        return slot * np.int32(b * b) + (ix & (b - 1)) * np.int32(b) + (iy & (b - 1))

    def local(self, x: float, y: float, reach: float) -> World:
        """A dense ``World`` of the (2k+1) x (2k+1) tiles around the tile of (x, y) that hold
        every pixel within ``reach`` of it (empty where the corridor has no tile); the last one
        is kept, so a sensor moving within a tile copies nothing."""
        t = self.tile_px * self.resolution
        a = int(np.floor((x - self.origin[0]) / t))
        b = int(np.floor((y - self.origin[1]) / t))
        k = int(np.ceil(reach / t))
        if self._window and self._window[0] == (a, b, k):
            return self._window[1]
        ia, ib = np.arange(a - k, a + k + 1), np.arange(b - k, b + k + 1)
        inside = ((ia >= 0) & (ia < self.tiles.shape[0]))[:, None] & \
            ((ib >= 0) & (ib < self.tiles.shape[1]))[None, :]
        slots = np.where(inside, self.tiles[ia.clip(0, self.tiles.shape[0] - 1)[:, None],
                                            ib.clip(0, self.tiles.shape[1] - 1)[None, :]], 0)
        n = (2 * k + 1) * self.tile_px

        def dense(layer: np.ndarray) -> np.ndarray:
            return np.ascontiguousarray(layer[slots].transpose(0, 2, 1, 3).reshape(n, n))

        window = World(kind=self.kind, seed=self.seed, resolution=self.resolution,
                       origin=(self.origin[0] + (a - k) * t, self.origin[1] + (b - k) * t),
                       ground=dense(self.ground), height=dense(self.height),
                       rough=dense(self.rough), canopy_lo=dense(self.canopy_lo),
                       canopy_hi=dense(self.canopy_hi), material=dense(self.material))
        self._window = ((a, b, k), window)
        return window

    def ground_at(self, xy: np.ndarray) -> np.ndarray:
        i, j = self.cell_of(xy)
        return self.ground.ravel()[self.flat_index(i, j)].astype(np.float64)

    def fingerprint(self) -> str:
        """A short hash of the tiles, their places and the layers (without copying them)."""
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(self.tiles).tobytes())
        h.update(np.array(self.origin, np.float64).tobytes())
        for a in (self.ground, self.height, self.rough, self.canopy_lo, self.canopy_hi,
                  self.material):
            h.update(a if a.strides[0] else np.ascontiguousarray(a[0]))
        return h.hexdigest()[:16]


def densify(xy: np.ndarray, step: float) -> np.ndarray:
    """The polyline ``xy`` with points at most ``step`` apart (its own points kept)."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    seg = np.hypot(*np.diff(xy, axis=0).T)
    n = np.maximum(np.ceil(seg / step).astype(np.int64), 1)
    start = np.repeat(xy[:-1], n, axis=0)
    t = (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)) / np.repeat(n, n)
    return np.concatenate([start + t[:, None] * np.repeat(np.diff(xy, axis=0), n, axis=0),
                           xy[-1:]])


def corridor_tiles(xy: np.ndarray, half_width: float, tile_m: float) -> np.ndarray:
    """Tiles [K, 2] (integer (a, b): x in [a tile_m, (a+1) tile_m), y likewise), sorted, whose
    square comes within ``half_width`` metres of the polyline ``xy`` [N, 2]."""
    step = 0.25 * tile_m
    pts = densify(xy, step)
    r = int(np.ceil((half_width + step) / tile_m)) + 1
    da, db = np.mgrid[-r:r + 1, -r:r + 1]
    da, db = da.ravel(), db.ravel()
    found = []
    for c in range(0, len(pts), 4096):
        p = pts[c:c + 4096]
        a = np.floor(p[:, 0] / tile_m).astype(np.int64)[:, None] + da
        b = np.floor(p[:, 1] / tile_m).astype(np.int64)[:, None] + db
        gx = np.maximum(np.maximum(a * tile_m - p[:, :1], p[:, :1] - (a + 1) * tile_m), 0.0)
        gy = np.maximum(np.maximum(b * tile_m - p[:, 1:], p[:, 1:] - (b + 1) * tile_m), 0.0)
        near = gx * gx + gy * gy <= (half_width + 0.5 * step) ** 2
        found.append(np.stack([a[near], b[near]], axis=1))
    return np.unique(np.concatenate(found), axis=0)
