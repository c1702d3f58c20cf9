"""The shared-tile store's host-side accounting: the bytes it allocates and holds, and the
errors its status bits stand for. Nothing here runs under jit; the store itself is
``tilestore``."""

from __future__ import annotations

import math

from jax import Array

from gslam_jax.errors import InputError
from gslam_jax.rbpf import unknown
from gslam_jax.rbpf.tilestore import POOL_EXHAUSTED, WINDOW_EXCEEDED, TileStore, pages_per_side

__all__ = ["PoolExhaustedError", "tile_bytes", "nbytes", "peak_bytes", "check_status"]


class PoolExhaustedError(InputError):
    """The shared-tile pool ran out of tiles (``[map] pool_tiles``)."""


def tile_bytes(store: TileStore) -> int:
    """Bytes of one pool tile: its k, S, known-cell bits and their counts."""
    return sum(x.dtype.itemsize * math.prod(x.shape[1:])
               for x in (store.kpool, store.spool, store.bpool, store.cpool))


def nbytes(num_particles: int, map_shape: tuple[int, int], tile: int, pool_tiles: int,
           bits: bool) -> int:
    """Bytes ``init`` allocates: the pool with its zero tile (k, S and, with ``bits``, the
    known-cell bits of each tile and their counts per row of blocks), the page tables, the
    reference counts and the free stack."""
    T, B = tile, unknown.BLOCK
    bit_bytes = ((T // B) ** 2 * 2 * 4 + (T // B) * 4) if bits else 0
    ty, tx = pages_per_side(map_shape, T)
    return (pool_tiles + 1) * (T * T * 2 * 4 + bit_bytes) + 4 * (num_particles * ty * tx
                                                                 + 2 * pool_tiles)


def peak_bytes(store: TileStore) -> int:
    """Most bytes the store held at once (``nbytes`` less the tiles never live together): its
    peak of live tiles plus the page tables and bookkeeping (host side: reads ``peak``)."""
    J, ty, tx = store.page.shape
    P, T = store.refcount.shape[0], store.kpool.shape[1]
    allocated = nbytes(J, (ty * T, tx * T), T, P, bits=store.bpool.shape[1] > 0)
    return allocated - (P + 1 - int(store.peak)) * tile_bytes(store)


def check_status(status: int | Array, pool_tiles: int, where: str = "",
                 automatic: bool = False) -> None:
    """Raise the host-side error for a store's ``status`` bits (0: fine); ``automatic``: the
    pool was sized (and grown between chunks) by the caller, not by ``[map] pool_tiles``."""
    status = int(status)
    if status & POOL_EXHAUSTED:
        raise PoolExhaustedError(where + (
            f"the shared map store's automatic pool of {pool_tiles} tiles ran out, and the "
            f"memory has no room to grow it (it grows as far as the memory allows); set "
            f"[map] pool_tiles to a fixed size above {pool_tiles}" if automatic else
            f"the shared map store ran out of tiles: [map] pool_tiles = {pool_tiles} is too "
            f"small for this run; raise [map] pool_tiles") + " (or use [map] store = \"dense\")")
    if status & WINDOW_EXCEEDED:
        raise RuntimeError(f"{where}an update wrote cells farther apart than the shared store's "
                           f"page window allows (a bug: the window comes from the local map's "
                           f"reach)")
