"""Copy-on-write tiled maps (paper 6.3): the map storage of the original C implementation.

The global map is cut into square tiles of ``side`` cells. A particle's map is a dict from tile
coordinate to a reference-counted ``Tile``; a tile is allocated when a cell in it is first
written, so unvisited space costs nothing. Resampling copies only the dict (each tile's count
goes up); the first write to a tile held by more than one map makes a private copy. A
``Ledger`` keeps the bytes held by live tiles: their cells (k, S) and, in "sample" mode, their
known-cell caches (``Tile.known``), the latter also on their own (``Ledger.cache_bytes``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["tile_cells", "Ledger", "Tile", "TileMap"]

F32 = np.float32


def tile_cells(tile_size: float, resolution: float) -> int:
    """Tile side in cells; rejects a tile size that is not a whole number of cells."""
    if not (tile_size > 0 and resolution > 0):
        raise ValueError(f"tile size {tile_size} m and resolution {resolution} m must be positive")
    n = tile_size / resolution
    side = round(n)
    if side < 1 or abs(n - side) > 1e-6 * max(1.0, n):
        lo, hi = max(1, math.floor(n)), math.ceil(n)
        raise ValueError(
            f"tile size {tile_size} m is {n:.4g} cells at resolution {resolution} m, not a whole "
            f"number of cells; use e.g. {lo * resolution:.6g} m ({lo} cells) or "
            f"{hi * resolution:.6g} m ({hi} cells)")
    return int(side)


@dataclass
class Ledger:
    """Bytes and count of live tiles, shared by all maps of one filter.

    ``live_bytes`` (and its maximum ``peak_bytes``) is everything the tiles hold: cells (k, S)
    and known-cell caches; ``cache_bytes`` is the caches' part of it.
    """

    live_bytes: int = 0
    live_tiles: int = 0
    peak_bytes: int = 0
    allocations: int = 0
    copies: int = 0
    cache_bytes: int = 0

    def add(self, nbytes: int, copy: bool) -> None:
        self.live_bytes += nbytes
        self.live_tiles += 1
        self.allocations += 1
        self.copies += int(copy)
        self.peak_bytes = max(self.peak_bytes, self.live_bytes)

    def free(self, nbytes: int) -> None:
        self.live_bytes -= nbytes
        self.live_tiles -= 1

    def cache(self, nbytes: int) -> None:
        """A tile's known-cell cache was built."""
        self.live_bytes += nbytes
        self.cache_bytes += nbytes
        self.peak_bytes = max(self.peak_bytes, self.live_bytes)

    def uncache(self, nbytes: int) -> None:
        """A tile's known-cell cache was dropped."""
        self.live_bytes -= nbytes
        self.cache_bytes -= nbytes


class Tile:
    """k and S of ``side`` x ``side`` cells, with a count of the maps that hold it and, once
    ``known`` was asked, a cache of its known cells (counted in the ledger passed to ``known``)."""

    __slots__ = ("k", "S", "refs", "_known")

    def __init__(self, k: np.ndarray, S: np.ndarray):
        self.k, self.S = k, S
        self.refs = 1
        self._known: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    @property
    def nbytes(self) -> int:
        """Bytes of the cells (k, S); the known-cell cache is ``cache_nbytes``."""
        return self.k.nbytes + self.S.nbytes

    @property
    def cache_nbytes(self) -> int:
        return sum(a.nbytes for a in self._known) if self._known is not None else 0

    def known(self, i0: int, j0: int, blocks_w: int, ledger: Ledger | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Known cells (k > 0) as (order keys, k, S), sorted by key; cached until written
        (``drop_known``), the cache's bytes counted in ``ledger``.

        The key orders cells by 8 x 8 block, blocks row-major over a map ``blocks_w`` blocks
        wide, and row-major inside a block; (i0, j0) is the tile's first global cell.
        """
        if self._known is None:
            ii, jj = np.nonzero(self.k > 0)
            gi, gj = ii + i0, jj + j0
            keys = ((gi // 8) * blocks_w + gj // 8) * 64 + (gi % 8) * 8 + gj % 8
            order = np.argsort(keys, kind="stable")
            self._known = (keys[order].astype(np.int64), self.k[ii, jj][order], self.S[ii, jj][order])
            if ledger is not None:
                ledger.cache(self.cache_nbytes)
        return self._known

    def drop_known(self, ledger: Ledger | None = None) -> None:
        """Forget the known-cell cache (the cells are about to change, or the tile is freed)."""
        if self._known is not None:
            if ledger is not None:
                ledger.uncache(self.cache_nbytes)
            self._known = None


@dataclass
class TileMap:
    """One particle's map: tile coordinate -> Tile (tiles may be shared with other maps)."""

    side: int
    ledger: Ledger
    tiles: dict[tuple[int, int], Tile] = field(default_factory=dict)

    def share(self) -> "TileMap":
        """A copy that shares every tile (resampling); no cell data is copied."""
        for t in self.tiles.values():
            t.refs += 1
        return TileMap(self.side, self.ledger, dict(self.tiles))

    def release(self) -> None:
        """Drop this map's hold on its tiles; tiles no map holds are freed."""
        for t in self.tiles.values():
            t.refs -= 1
            if t.refs == 0:
                t.drop_known(self.ledger)
                self.ledger.free(t.nbytes)
        self.tiles = {}

    def _spans(self, i0: int, j0: int, h: int, w: int):
        """(tile coord, slice in tile, slice in window) for every tile the window overlaps."""
        T = self.side
        for ti in range(i0 // T, (i0 + h - 1) // T + 1):
            a0, a1 = max(i0, ti * T), min(i0 + h, (ti + 1) * T)
            for tj in range(j0 // T, (j0 + w - 1) // T + 1):
                b0, b1 = max(j0, tj * T), min(j0 + w, (tj + 1) * T)
                yield ((ti, tj), (slice(a0 - ti * T, a1 - ti * T), slice(b0 - tj * T, b1 - tj * T)),
                       (slice(a0 - i0, a1 - i0), slice(b0 - j0, b1 - j0)))

    def read(self, i0: int, j0: int, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
        """(k, S) of the window of cells [i0, i0 + h) x [j0, j0 + w); unallocated cells are 0."""
        k = np.zeros((h, w), F32)
        S = np.zeros((h, w), F32)
        for coord, in_tile, in_win in self._spans(i0, j0, h, w):
            t = self.tiles.get(coord)
            if t is not None:
                k[in_win], S[in_win] = t.k[in_tile], t.S[in_tile]
        return k, S

    def _writable(self, coord: tuple[int, int]) -> Tile:
        t = self.tiles.get(coord)
        if t is None:  # first touch
            T = self.side
            t = Tile(np.zeros((T, T), F32), np.zeros((T, T), F32))
            self.ledger.add(t.nbytes, copy=False)
        elif t.refs > 1:  # copy on write
            t.refs -= 1
            t = Tile(t.k.copy(), t.S.copy())
            self.ledger.add(t.nbytes, copy=True)
        else:
            t.drop_known(self.ledger)
            return t
        self.tiles[coord] = t
        return t

    def add(self, i0: int, j0: int, k_obs: np.ndarray, S_obs: np.ndarray) -> None:
        """Conjugate update (eq. 14) k'' = k' + k, S'' = S' + S of a window; tiles where the
        observation has no informative cell are neither allocated nor copied."""
        h, w = k_obs.shape
        for coord, in_tile, in_win in self._spans(i0, j0, h, w):
            ko = k_obs[in_win]
            if not np.any(ko > 0):
                continue
            t = self._writable(coord)
            t.k[in_tile] = t.k[in_tile] + ko
            t.S[in_tile] = t.S[in_tile] + S_obs[in_win]

    def known_cells(self, blocks_w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All known cells of the map in the sampler's order (8 x 8 blocks row-major, then
        row-major inside a block): (keys, k, S). Each tile's part is cached in the tile (and
        counted in the ledger) until the tile is written."""
        T = self.side
        parts = [t.known(ti * T, tj * T, blocks_w, self.ledger)
                 for (ti, tj), t in self.tiles.items()]
        if not parts:
            e = np.zeros(0)
            return e.astype(np.int64), e.astype(F32), e.astype(F32)
        keys = np.concatenate([p[0] for p in parts])
        order = np.argsort(keys, kind="stable")  # merges the sorted runs
        return (keys[order], np.concatenate([p[1] for p in parts])[order],
                np.concatenate([p[2] for p in parts])[order])

    def dense(self, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """The map as dense (k, S) arrays of ``shape`` (for comparison and output)."""
        return self.read(0, 0, *shape)
