"""Dense map store: every particle owns whole [H, W] maps of k and S.

Simple to index, and the fastest store while the maps fit in memory; but memory grows with
particles x map area, and resampling copies the maps of the particles left without offspring
(``gather_particles``). ``tilestore`` shares tiles between particles instead; ``rbpf.maps``
chooses between the two. "sample" mode also keeps each map's known-cell bitmasks
(``unknown.pack_known``) and their counts per segment (``unknown.segment_counts``, which
``sample_known`` draws eq. 31's known cells from), refreshed around every footprint after a
write (``finish_update``).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array, lax

from gslam_jax.rbpf import unknown
from gslam_jax.rbpf.types import FilterConfig

__all__ = ["DenseMaps", "ROW_BAND", "init", "nbytes", "read_cells", "add_to_cells", "read",
           "add", "known_bits", "sample_known", "window_origin", "written_rows", "finish_update",
           "gather_particles", "resample"]

ROW_BAND = 64  # map rows per copy when resampling copies only the written rows


class DenseMaps(NamedTuple):
    """The maps of J particles, one whole [H, W] map each."""

    k: Array           # [J, H, W] float32 degrees of freedom k
    S: Array           # [J, H, W] float32 sums of squared deviations S
    known_bits: Array  # [J, H/8, W/8, 2] uint32 known-cell bits ("sample" mode; else [J, 0, 0, 2])
    # [J, H/8, ceil(W/8 / SEGMENT)] int32 known cells per segment (``unknown.segment_counts``;
    # else [J, 0, 0])
    known_counts: Array
    rows: Array        # [2] int32 map rows [lo, hi) that any update may have written so far


def init(num_particles: int, map_shape: tuple[int, int], bits: bool,
         prior: tuple[Array, Array] | None = None) -> DenseMaps:
    """J empty maps (every cell unknown), or J copies of the map ``prior`` = (k, S) [H, W].
    ``bits``: keep known-cell bitmasks. The written rows start empty either way: rows no
    update wrote hold the same values (zeros or the prior) in every particle's map."""
    H, W = map_shape
    shape = (num_particles, H, W)
    nb = (H // unknown.BLOCK, W // unknown.BLOCK) if bits else (0, 0)
    if prior is None:
        k, S = jnp.zeros(shape, jnp.float32), jnp.zeros(shape, jnp.float32)
        one = jnp.zeros(nb + (2,), jnp.uint32)
    else:
        pk, pS = (jnp.asarray(x, jnp.float32) for x in prior)
        k, S = jnp.broadcast_to(pk, shape), jnp.broadcast_to(pS, shape)
        one = unknown.pack_known(pk > 0) if bits else jnp.zeros(nb + (2,), jnp.uint32)
    counts = unknown.segment_counts(one) if bits else jnp.zeros((0, 0), jnp.int32)
    return DenseMaps(k=k, S=S, known_bits=jnp.broadcast_to(one, (num_particles,) + one.shape),
                     known_counts=jnp.broadcast_to(counts, (num_particles,) + counts.shape),
                     rows=jnp.array([H, 0], jnp.int32))


def nbytes(num_particles: int, map_shape: tuple[int, int], bits: bool) -> int:
    """Bytes ``init`` allocates for the maps: k and S [J, H, W] float32, plus the known-cell
    bits [J, H/8, W/8, 2] uint32 and their segment counts with ``bits`` (resampling copies
    them in place)."""
    H, W = map_shape
    B = unknown.BLOCK
    segments = -(-(W // B) // unknown.SEGMENT)
    bit_bytes = (H // B) * ((W // B) * 2 * 4 + segments * 4) if bits else 0
    return num_particles * (H * W * 2 * 4 + bit_bytes)


def _flat(maps: Array) -> Array:
    """[J, H, W] -> [J, H*W], the layout ``read_cells`` and ``add_to_cells`` index."""
    return maps.reshape(maps.shape[0], -1)


def _indices(maps: Array, rows: Array, cells_: Array) -> tuple[Array, ...]:
    """Index of cells_[i, m] of particle rows[i] in ``maps`` [J, H*W]: one flat index into
    ``maps.reshape(-1)`` where J*H*W fits int32 (a 1-D gather or scatter is cheaper on CPU
    than a batched one), else the (row, cell) pair."""
    J, HW = maps.shape
    if J * HW < 2 ** 31:
        return (rows[:, None] * HW + cells_,)
    return jnp.broadcast_to(rows[:, None], cells_.shape), cells_


def read_cells(maps: Array, rows: Array, cells_: Array, on_map: Array) -> Array:
    """maps[rows[i], cells_[i, m]] where on_map, else 0 ([J, H*W], [n], [n, M] -> [n, M])."""
    idx = _indices(maps, rows, jnp.where(on_map, cells_, 0))
    flat = maps.reshape(-1) if len(idx) == 1 else maps
    return jnp.where(on_map, flat.at[idx].get(mode="promise_in_bounds"), 0.0)


def add_to_cells(maps: Array, rows: Array, cells_: Array, values: Array) -> Array:
    """maps[rows[i], cells_[i, m]] += values[m] (eq. 14); cells_ >= H*W (off the map) skipped.

    Skipped entries add 0 to cell 0 instead of being dropped as out of bounds, so the scatter
    can promise in-bounds indices: no bounds check per element."""
    on_map = cells_ < maps.shape[1]
    idx = _indices(maps, rows, jnp.where(on_map, cells_, 0))
    vals = jnp.where(on_map, jnp.broadcast_to(values, cells_.shape), 0.0)
    if len(idx) == 1:
        return maps.reshape(-1).at[idx].add(vals, mode="promise_in_bounds").reshape(maps.shape)
    return maps.at[idx].add(vals, mode="promise_in_bounds")


def read(store: DenseMaps, particles: Array, cells_: Array, on_map: Array
         ) -> tuple[Array, Array]:
    """(k, S) [n, M] at flat map cells cells_ [n, M] of particles [n]; 0 where not on_map."""
    return (read_cells(_flat(store.k), particles, cells_, on_map),
            read_cells(_flat(store.S), particles, cells_, on_map))


def add(store: DenseMaps, particles: Array, cells_: Array, k: Array, S: Array) -> DenseMaps:
    """Eq. 14: add (k, S) [M] at flat map cells cells_ [n, M] (H*W: off the map, skipped) of
    particles [n]."""
    shape = store.k.shape
    return store._replace(k=add_to_cells(_flat(store.k), particles, cells_, k).reshape(shape),
                          S=add_to_cells(_flat(store.S), particles, cells_, S).reshape(shape))


def known_bits(store: DenseMaps, rows: Array) -> Array:
    """Known-cell bits [n, H/8, W/8, 2] of particles ``rows`` [n]."""
    return jnp.take(store.known_bits, rows, axis=0)


def sample_known(store: DenseMaps, rows: Array, u: Array, width: int) -> tuple[Array, Array]:
    """Eq. 31's uniform known cells of the maps of particles ``rows`` [n], one per uniform of
    ``u`` [n, S]: (flat cells [n, S], known cells [n]), as ``unknown.sample_known_cells``
    draws them, from the segment counts (``unknown.sample_by_segments``)."""

    def one(j: Array, v: Array) -> tuple[Array, Array]:
        Wb = store.known_bits.shape[2]
        n = unknown.SEGMENT

        def words(row: Array, col: Array) -> Array:
            block = col[:, None] * n + jnp.arange(n)  # [S, n]; past the map's edge: empty
            w = store.known_bits[j, row[:, None], jnp.minimum(block, Wb - 1)]
            return jnp.where((block < Wb)[..., None], w, jnp.uint32(0))

        return unknown.sample_by_segments(store.known_counts[j], words, v, width)

    return jax.vmap(one)(rows, u)


def window_origin(pose: Array, cfg: FilterConfig) -> tuple[Array, Array, Array]:
    """Top-left cell (i, j) of the block-aligned window that holds a particle's footprint.

    The known-cell bits are refreshed over this window after a write. The ideal window is
    centred on the particle's cell (aligned to ``cfg.block``); a window that would leave the
    map is shifted back inside and flagged, never wrapped.
    """
    H, W = cfg.map_shape
    Wn, b = cfg.window, cfg.block
    ci = jnp.floor((pose[0] - cfg.map_origin[0]) / cfg.resolution).astype(jnp.int32)
    cj = jnp.floor((pose[1] - cfg.map_origin[1]) / cfg.resolution).astype(jnp.int32)
    oi = ((ci - Wn // 2) // b) * b
    oj = ((cj - Wn // 2) // b) * b
    ci_, cj_ = jnp.clip(oi, 0, H - Wn), jnp.clip(oj, 0, W - Wn)
    return ci_, cj_, (ci_ != oi) | (cj_ != oj)


def written_rows(rows: Array, pose: Array, cfg: FilterConfig) -> Array:
    """``rows`` [lo, hi) widened to every map row an update from ``pose`` [J, 3] can write
    (``FilterConfig.reach`` rows either side of each particle's row)."""
    H, reach = cfg.map_shape[0], cfg.reach
    r = jnp.floor((pose[:, 0] - cfg.map_origin[0]) / cfg.resolution)
    r = jnp.clip(jnp.nan_to_num(r, nan=0.0), -reach, H + reach).astype(jnp.int32)
    return jnp.stack([jnp.maximum(jnp.minimum(rows[0], jnp.min(r) - reach), 0),
                      jnp.minimum(jnp.maximum(rows[1], jnp.max(r) + reach + 1), H)])


def finish_update(store: DenseMaps, pose: Array, cfg: FilterConfig) -> DenseMaps:
    """After an update from ``pose`` [J, 3] wrote the maps: the known-cell bits refreshed
    around each footprint ("sample" mode), with the segment counts of the rows of blocks they
    lie in, and the written rows widened (``written_rows``)."""
    bits, counts = store.known_bits, store.known_counts
    if cfg.unknown_cells == "sample" and cfg.update_map:

        def refresh(k, bits, counts, pose):
            b, Wn = unknown.BLOCK, cfg.window
            oi, oj, _ = window_origin(pose, cfg)
            known = lax.dynamic_slice(k, (oi, oj), (Wn, Wn)) > 0
            bits = lax.dynamic_update_slice(bits, unknown.pack_known(known),
                                            (oi // b, oj // b, 0))
            band = lax.dynamic_slice_in_dim(bits, oi // b, Wn // b)  # whole rows of blocks
            counts = lax.dynamic_update_slice_in_dim(counts, unknown.segment_counts(band),
                                                     oi // b, 0)
            return bits, counts

        bits, counts = jax.vmap(refresh)(store.k, bits, counts, pose)
    return store._replace(known_bits=bits, known_counts=counts,
                          rows=written_rows(store.rows, pose, cfg))


def gather_particles(particles, ancestors: Array, rows: Array | None = None):
    """``x[ancestors]`` for every array of the pytree ``particles`` ([J, ...] leaves), in place.

    ``ancestors`` must keep every surviving particle in its own slot (``resampling.
    keep_in_place``): then only the slots of particles without offspring are overwritten, one
    [H, W] map at a time, from slots that are never overwritten. No second [J, H, W] buffer is
    allocated, and only the dead particles' maps are copied (about a third of J for uniform
    weights) instead of all J. With ``rows`` [lo, hi) (``DenseMaps.rows``), the [J, H, W]
    leaves are copied only over those rows, in bands of ``ROW_BAND``: no update has written
    the others, which are zero in every map.
    """
    J = ancestors.shape[0]
    moved = ancestors != jnp.arange(J, dtype=ancestors.dtype)
    slots = jnp.nonzero(moved, size=J, fill_value=0)[0]

    def whole(x, src, dst):
        return lax.dynamic_update_index_in_dim(
            x, lax.dynamic_index_in_dim(x, src, keepdims=False), dst, 0)

    def banded(x, src, dst):
        H, W = x.shape[1:]
        band = min(ROW_BAND, H)

        def one_band(b, x):
            start = jnp.minimum(rows[0] + b * band, H - band)
            piece = lax.dynamic_slice(x, (src, start, 0), (1, band, W))
            return lax.dynamic_update_slice(x, piece, (dst, start, 0))

        return lax.fori_loop(0, (rows[1] - rows[0] + band - 1) // band, one_band, x)

    def copy_one(n, particles):
        dst = slots[n]
        src = ancestors[dst]
        return jax.tree.map(
            lambda x: banded(x, src, dst) if rows is not None and x.ndim == 3
            else whole(x, src, dst), particles)

    return lax.fori_loop(0, jnp.sum(moved), copy_one, particles)


def resample(store: DenseMaps, ancestors: Array) -> DenseMaps:
    """Particle i takes the maps of particle ancestors[i] (survivors kept in place,
    ``resampling.keep_in_place``): the dead particles' maps copied over the written rows."""
    k, S = gather_particles((store.k, store.S), ancestors, store.rows)
    bits, counts = gather_particles((store.known_bits, store.known_counts), ancestors)
    return store._replace(k=k, S=S, known_bits=bits, known_counts=counts)
