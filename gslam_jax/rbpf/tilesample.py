"""Eq. 31's uniform known cells, drawn from the shared-tile store without whole-map scans.

``unknown.sample_known_cells`` ranks a map's known cells in the order of its 8 x 8 blocks (rows
of blocks top to bottom, blocks left to right, bits within a block) and finds the block of rank
r from the cumulative counts of every block: O(H W / 64) per particle and update, with the
whole map's bits gathered out of the pool first. The store keeps, beside each tile's bits,
its known cells per row of blocks (``TileStore.cpool``, refreshed with the bits), so a map's
counts per *segment* (one row of blocks within one tile: T/8 blocks) are a gather of its page
table's entries. The same order is the segments' (row of blocks, then tile column), then the
blocks within the segment, so the rank r = floor(u * #known) names exactly the cell the dense
store's sampler draws: the two stores stay bit-identical. The work is O(H W / (64 T / 8)) per
particle for the counts, and T/8 blocks per drawn cell.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array, lax

from gslam_jax.rbpf import unknown
from gslam_jax.rbpf.tilestore import TileStore

__all__ = ["sample_known"]


def _one_map(store: TileStore, page: Array, u: Array, width: int) -> tuple[Array, Array]:
    """(flat cells with the shape of u [S], number of known cells) of the map of one page
    table ``page`` [ty, tx]; cells of a map ``width`` cells wide."""
    nb = store.cpool.shape[1]  # blocks per tile side
    B = unknown.BLOCK
    ty, tx = page.shape
    seg = store.cpool[page].transpose(0, 2, 1).reshape(-1)  # [(ty * nb) * tx]: (block row, tile)
    cum = jnp.cumsum(seg)
    total = cum[-1]
    r = unknown.uniform_rank(u, total)
    s = jnp.clip(jnp.searchsorted(cum, r, side="right"), 0, seg.shape[0] - 1)
    rank = r - (cum[s] - seg[s])
    block_row, tile_col = s // tx, s % tx
    tile = page[block_row // nb, tile_col]
    words = store.bpool[tile, block_row % nb]  # [S, nb, 2]: the segment's blocks
    counts = jnp.sum(lax.population_count(words).astype(jnp.int32), axis=-1)  # [S, nb]
    ccum = jnp.cumsum(counts, axis=-1)
    b = jnp.minimum(jnp.sum(ccum <= rank[:, None], axis=-1), nb - 1)  # first ccum > rank
    take = jnp.take_along_axis
    in_block = rank - (take(ccum, b[:, None], -1)[:, 0] - take(counts, b[:, None], -1)[:, 0])
    lo = take(words[..., 0], b[:, None], -1)[:, 0]
    hi = take(words[..., 1], b[:, None], -1)[:, 0]
    pos = unknown.select_in_block(lo, hi, in_block)
    row = block_row * B + pos // B
    col = (tile_col * nb + b) * B + pos % B
    return row * width + col, total


def sample_known(store: TileStore, particles: Array, u: Array, map_shape: tuple[int, int]
                 ) -> tuple[Array, Array]:
    """Uniform known cells of the maps of ``particles`` [n], one per uniform of ``u`` [n, S]:
    (flat cells of the [H, W] map [n, S], known cells [n]); the cells
    ``unknown.sample_known_cells`` draws from the same map and uniforms. Where a map has no
    known cell the cells are meaningless; callers mask on the count."""
    return jax.vmap(lambda p, v: _one_map(store, p, v, map_shape[1]))(store.page[particles], u)
