"""Sampler of known cells for the unknown-cell model (paper 6.2.2, eq. 31).

Each cell of an observation that a particle has never seen borrows the statistics (k', S') of a
uniformly random *known* cell of that particle's map. Scanning a dense [H, W] map for its known
cells at every update would cost O(H W); instead each particle keeps a bitmask of its known cells
in 8 x 8 blocks (two uint32 words per block), maintained for the updated window only. A uniform
known cell is then: a uniform rank r in [0, #known), the block holding rank r by binary search on
the cumulative block counts, and the r-th set bit of that block's 64-bit mask by popcounts.
Given the rank, the mapping to cells is exact (every rank names one known cell). The rank
comes from a float32 uniform u on a grid of 2^-23, as r = floor(u * #known): each known cell
gets probability 1 / #known to within a relative 1 / floor(2^23 / #known) (5 % for a whole
640 x 640 map known, 0.4 % for 30,000 known cells), and above 2^23 known cells some are never
drawn.

Both stores draw the same cells without scanning whole maps (``sample_by_segments``): they
keep the known cells of every *segment*, a run of consecutive blocks of one row of blocks
(``SEGMENT`` blocks in the dense store, one tile's width in the shared store), find the segment
of rank r from the cumulative segment counts, then the block within it. The order of the ranks
is the same, so a uniform names the same cell as ``sample_known_cells``.
"""

from __future__ import annotations

from typing import Callable

import jax.numpy as jnp
from jax import Array, lax

__all__ = ["BLOCK", "SEGMENT", "pack_known", "segment_counts",
           "uniform_rank", "select_in_block", "sample_known_cells", "sample_by_segments"]

BLOCK = 8  # block side in cells; 64 cells = two uint32 words
SEGMENT = 4  # blocks per segment of the dense store's counts (``segment_counts``)


def pack_known(known: Array) -> Array:
    """Bool [H, W] (H, W multiples of 8) -> uint32 [H/8, W/8, 2] bitmasks (bit = r * 8 + c)."""
    H, W = known.shape
    blocks = known.reshape(H // BLOCK, BLOCK, W // BLOCK, BLOCK).transpose(0, 2, 1, 3)
    bits = blocks.reshape(H // BLOCK, W // BLOCK, 2, 32).astype(jnp.uint32)
    shifts = jnp.arange(32, dtype=jnp.uint32)
    # Disjoint bits, so the sum is the bitwise OR.
    return jnp.sum(bits << shifts, axis=-1, dtype=jnp.uint32)


def segment_counts(bits: Array, segment: int = SEGMENT) -> Array:
    """Known cells per segment of ``segment`` blocks: uint32 [..., Hb, Wb, 2] -> int32
    [..., Hb, ceil(Wb / segment)] (the last segment of a row padded with empty blocks)."""
    per_block = jnp.sum(lax.population_count(bits).astype(jnp.int32), axis=-1)
    Wb = per_block.shape[-1]
    pad = -Wb % segment
    per_block = jnp.pad(per_block, [(0, 0)] * (per_block.ndim - 1) + [(0, pad)])
    return per_block.reshape(per_block.shape[:-1] + (-1, segment)).sum(-1)


def uniform_rank(u: Array, total: Array) -> Array:
    """The rank floor(u * total) of a known cell, in [0, total - 1] (0 when total is 0)."""
    return jnp.clip(jnp.floor(u * total.astype(u.dtype)).astype(jnp.int32), 0,
                    jnp.maximum(total - 1, 0))


def _select_bit(word: Array, rank: Array) -> Array:
    """Position of the ``rank``-th (0-based) set bit of each uint32 ``word``."""
    pos = jnp.zeros_like(rank)
    for width in (16, 8, 4, 2, 1):
        low = lax.population_count(word & jnp.uint32((1 << width) - 1)).astype(rank.dtype)
        go = rank >= low
        rank = jnp.where(go, rank - low, rank)
        word = jnp.where(go, word >> jnp.uint32(width), word)
        pos = jnp.where(go, pos + width, pos)
    return pos


def select_in_block(lo: Array, hi: Array, rank: Array) -> Array:
    """Position (bit r * 8 + c) of the ``rank``-th known cell of a block's two words."""
    count_lo = lax.population_count(lo).astype(rank.dtype)
    return jnp.where(rank < count_lo, _select_bit(lo, rank),
                     32 + _select_bit(hi, rank - count_lo))


def sample_known_cells(bits: Array, u: Array) -> tuple[Array, Array]:
    """Uniform known cells of one map from its block bitmasks.

    Args:
        bits: uint32 [Hb, Wb, 2] from ``pack_known`` (map of [8 Hb, 8 Wb] cells).
        u: uniforms in [0, 1), any shape; one cell per uniform.
    Returns:
        (flat cell indices into the [H, W] map with the shape of u, number of known cells).
        Where the map has no known cell the indices are meaningless; callers mask on the count.
    """
    Hb, Wb, _ = bits.shape
    lo = bits[..., 0].reshape(-1)
    hi = bits[..., 1].reshape(-1)
    counts = (lax.population_count(lo) + lax.population_count(hi)).astype(jnp.int32)
    cum = jnp.cumsum(counts)
    total = cum[-1]
    r = uniform_rank(u, total)
    block = jnp.clip(jnp.searchsorted(cum, r, side="right"), 0, cum.shape[0] - 1)
    pos = select_in_block(lo[block], hi[block], r - (cum[block] - counts[block]))
    row = (block // Wb) * BLOCK + pos // BLOCK
    col = (block % Wb) * BLOCK + pos % BLOCK
    return row * (Wb * BLOCK) + col, total


def sample_by_segments(seg: Array, words: Callable[[Array, Array], Array], u: Array,
                       width: int) -> tuple[Array, Array]:
    """``sample_known_cells`` from segment counts, without the whole map's bits.

    Args:
        seg: int32 [R, C] known cells of segment (r, c): blocks c * n .. c * n + n - 1 of row
            of blocks r (n blocks per segment; blocks past the map's edge are empty).
        words: (r [S], c [S]) -> uint32 [S, n, 2], the words of those segments' blocks.
        u: uniforms [S], one cell each.
        width: the map's width in cells.
    Returns:
        (flat cell indices [S], number of known cells), as ``sample_known_cells`` gives for
        the same map and uniforms.
    """
    R, C = seg.shape
    flat = seg.reshape(-1)
    cum = jnp.cumsum(flat)
    total = cum[-1]
    r = uniform_rank(u, total)
    s = jnp.clip(jnp.searchsorted(cum, r, side="right"), 0, R * C - 1)
    rank = r - (cum[s] - flat[s])
    row, col = s // C, s % C
    w = words(row, col)  # [S, n, 2]
    n = w.shape[-2]
    counts = jnp.sum(lax.population_count(w).astype(jnp.int32), axis=-1)  # [S, n]
    ccum = jnp.cumsum(counts, axis=-1)
    b = jnp.minimum(jnp.sum(ccum <= rank[:, None], axis=-1), n - 1)[:, None]  # first > rank
    pick = jnp.take_along_axis
    in_block = rank - (pick(ccum, b, -1) - pick(counts, b, -1))[:, 0]
    pos = select_in_block(pick(w[..., 0], b, -1)[:, 0], pick(w[..., 1], b, -1)[:, 0], in_block)
    cell_row = row * BLOCK + pos // BLOCK
    cell_col = (col * n + b[:, 0]) * BLOCK + pos % BLOCK
    return cell_row * width + cell_col, total
