"""Eq. 31's uniform known cells, drawn from the shared-tile store without whole-map scans.

``unknown.sample_known_cells`` ranks a map's known cells in the order of its 8 x 8 blocks and
finds the block of rank r from the cumulative counts of every block: O(H W / 64) per particle
and update, with the whole map's bits gathered out of the pool first. The pool keeps, beside
each tile's bits, its known cells per row of blocks (``TileStore.cpool``, refreshed with the
bits): the counts of a map's segments (one row of blocks within one tile) are then a gather of
its page table's entries, and ``unknown.sample_by_segments`` draws the same cells from them.
"""

from __future__ import annotations

import jax
from jax import Array

from gslam_jax.rbpf import unknown
from gslam_jax.rbpf.tilestore import TileStore

__all__ = ["sample_known"]


def _one_map(store: TileStore, page: Array, u: Array, width: int) -> tuple[Array, Array]:
    """``unknown.sample_by_segments`` on the map of one page table ``page`` [ty, tx]."""
    nb = store.cpool.shape[1]  # blocks per tile side: the segments are a tile wide
    ty, tx = page.shape
    seg = store.cpool[page].transpose(0, 2, 1).reshape(ty * nb, tx)  # (row of blocks, tile)

    def words(row: Array, col: Array) -> Array:
        return store.bpool[page[row // nb, col], row % nb]  # [S, nb, 2]

    return unknown.sample_by_segments(seg, words, u, width)


def sample_known(store: TileStore, particles: Array, u: Array, map_shape: tuple[int, int]
                 ) -> tuple[Array, Array]:
    """Uniform known cells of the maps of ``particles`` [n], one per uniform of ``u`` [n, S]:
    (flat cells of the [H, W] map [n, S], known cells [n]); the cells
    ``unknown.sample_known_cells`` draws from the same map and uniforms. Where a map has no
    known cell the cells are meaningless; callers mask on the count."""
    return jax.vmap(lambda p, v: _one_map(store, p, v, map_shape[1]))(store.page[particles], u)
