"""Shared-tile map store: every particle's (k, S) map as pages into one pool of dense tiles.

The dense store keeps a whole [H, W] map per particle, so memory grows with particles x area
and resampling copies dead particles' maps. Here the global map is cut into tiles of T x T
cells; a fixed pool holds ``pool_tiles`` tiles of k and S (and, in "sample" mode, each tile's
known-cell bitmasks, ``unknown.pack_known``, and their counts per row of blocks, which
``tilesample`` draws eq. 31's known cells from), and each particle has a page table
[tiles_y, tiles_x] of pool indices. This is the paper's copy-on-write tile store (6.3; the
NumPy one is ``gslam_jax.tiled``) with static shapes, so it runs under jit, vmap and scan:

* a page that was never written points at the sentinel tile ``pool_tiles``, which is all
  zeros: reads there give k = S = 0 with no mask;
* before a block of particles adds its local maps (eq. 14), ``prepare`` gives each written
  page a tile of its own: a fresh tile (a copy of the zero sentinel) for an unwritten page, a
  copy of the tile for one held by other particles (reference count > 1; when every holder
  writes in the same block, one of them keeps the tile), the tile itself otherwise;
* resampling gathers the page tables by ancestor and recounts references; tiles left with no
  reference go back to the free stack.

Tiles come from a free stack (``free[:n_free]``); a block that needs more tiles than are free
changes nothing, writes nothing and sets ``status`` bit ``POOL_EXHAUSTED``: the host turns it
into an error naming ``[map] pool_tiles`` (``tilebytes.check_status``; ``tilebytes`` also
counts the store's bytes). Values are bit-identical to the dense store's: the same cells
receive the same additions in the same order.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array, lax

from gslam_jax.rbpf import unknown

__all__ = ["TileStore", "POOL_EXHAUSTED", "WINDOW_EXCEEDED", "init", "with_prior",
           "prior_tiles", "pages_per_side", "window_tiles", "pool_index", "read", "known_bits",
           "prepare", "add", "write", "resample", "grow", "to_dense", "live_tiles"]

POOL_EXHAUSTED = 1   # status bit: a block needed more fresh tiles than the pool had free
WINDOW_EXCEEDED = 2  # status bit: a particle's written cells spanned more pages than ``window``
COPY_CHUNK = 16      # tiles copied per step of the allocation loop


class TileStore(NamedTuple):
    """Maps of J particles as page tables into a pool of P = ``pool_tiles`` tiles.

    Pool tile P (one past the last) is the all-zero sentinel: never written, never freed.
    """

    kpool: Array     # [P + 1, T, T] float32 degrees of freedom k
    spool: Array     # [P + 1, T, T] float32 sums of squared deviations S
    bpool: Array     # [P + 1, T/8, T/8, 2] uint32 known-cell bits ([P + 1, 0, 0, 2] if unused)
    cpool: Array     # [P + 1, T/8] int32 known cells per row of blocks ([P + 1, 0] if unused)
    page: Array      # [J, tiles_y, tiles_x] int32 pool index of each page (P: never written)
    refcount: Array  # [P] int32 page-table entries pointing at each tile
    free: Array      # [P] int32 free tiles in free[:n_free]
    n_free: Array    # [] int32
    peak: Array      # [] int32 most tiles live at once (after any prepare)
    status: Array    # [] int32 sticky error bits (POOL_EXHAUSTED | WINDOW_EXCEEDED)


def pages_per_side(map_shape: tuple[int, int], tile: int) -> tuple[int, int]:
    """Page-table shape: tiles needed to cover the map (the last row / column may stick out)."""
    return -(-map_shape[0] // tile), -(-map_shape[1] // tile)


def window_tiles(reach: int, tile: int) -> int:
    """Most pages per side that cells within ``reach`` of one cell can fall in (2 reach + 1
    consecutive cells start anywhere in a tile)."""
    return math.ceil(2 * reach / tile) + 1


def init(num_particles: int, map_shape: tuple[int, int], tile: int, pool_tiles: int,
         bits: bool) -> TileStore:
    """Empty maps: every page unwritten, every tile free. ``bits``: keep known-cell bitmasks."""
    if tile % unknown.BLOCK:
        raise ValueError(f"tile side {tile} must be a multiple of {unknown.BLOCK} cells")
    if pool_tiles < 1:
        raise ValueError(f"pool_tiles {pool_tiles} must be at least 1")
    P, T = pool_tiles, tile
    if (P + 1) * T * T >= 2 ** 31:
        raise ValueError(f"pool_tiles {pool_tiles} of {T} x {T} cells exceeds the int32 cell "
                         f"index ({(2 ** 31) // (T * T) - 1} tiles at most)")
    nb = T // unknown.BLOCK if bits else 0
    return TileStore(
        kpool=jnp.zeros((P + 1, T, T), jnp.float32),
        spool=jnp.zeros((P + 1, T, T), jnp.float32),
        bpool=jnp.zeros((P + 1, nb, nb, 2), jnp.uint32),
        cpool=jnp.zeros((P + 1, nb), jnp.int32),
        page=jnp.full((num_particles,) + pages_per_side(map_shape, T), P, jnp.int32),
        refcount=jnp.zeros((P,), jnp.int32),
        free=jnp.arange(P, dtype=jnp.int32),
        n_free=jnp.int32(P),
        peak=jnp.int32(0),
        status=jnp.int32(0),
    )


def with_prior(store: TileStore, k: Array, S: Array) -> TileStore:
    """Every particle's map set to the one map (k, S) [H, W] (an empty ``store`` from
    ``init``): each tile of the map with a known cell (k > 0) is put in the pool once and every
    page table points at it (reference count J), so J particles hold one copy; the first write
    to such a page copies it (copy-on-write). Pages without a known cell stay unwritten. With
    more such tiles than the pool holds, nothing is placed and ``status`` has POOL_EXHAUSTED."""
    P, T = store.refcount.shape[0], _tile(store)
    J, ty, tx = store.page.shape
    H, W = k.shape

    def tiles(x: Array) -> Array:
        x = jnp.pad(jnp.asarray(x, jnp.float32), ((0, ty * T - H), (0, tx * T - W)))
        return x.reshape(ty, T, tx, T).transpose(0, 2, 1, 3).reshape(ty * tx, T, T)

    kt, st = tiles(k), tiles(S)
    used = jnp.any(kt > 0, axis=(1, 2))
    n = jnp.sum(used, dtype=jnp.int32)
    ok = n <= P
    slot = jnp.where(used & ok, jnp.cumsum(used, dtype=jnp.int32) - 1, P)
    put = jnp.where(slot < P, slot, P + 1)  # out of range: dropped by the scatters
    bpool, cpool = store.bpool, store.cpool
    if bpool.shape[1]:
        bits, counts = _known_cells(kt)
        bpool = bpool.at[put].set(bits, mode="drop")
        cpool = cpool.at[put].set(counts, mode="drop")
    placed = jnp.where(ok, n, 0)
    return store._replace(
        kpool=store.kpool.at[put].set(kt, mode="drop"),
        spool=store.spool.at[put].set(st, mode="drop"), bpool=bpool, cpool=cpool,
        page=jnp.broadcast_to(slot.reshape(ty, tx), (J, ty, tx)),
        refcount=jnp.zeros((P,), jnp.int32).at[slot].set(J, mode="drop"),
        free=(jnp.arange(P, dtype=jnp.int32) + placed) % P,
        n_free=P - placed, peak=placed,
        status=store.status | jnp.where(ok, 0, POOL_EXHAUSTED))


def prior_tiles(k, tile: int) -> int:
    """Pool tiles ``with_prior`` needs for the map k [H, W] (host side): tiles with k > 0."""
    known = np.asarray(k) > 0
    H, W = known.shape
    ty, tx = -(-H // tile), -(-W // tile)
    known = np.pad(known, ((0, ty * tile - H), (0, tx * tile - W)))
    return int(known.reshape(ty, tile, tx, tile).any(axis=(1, 3)).sum())


def _tile(store: TileStore) -> int:
    return store.kpool.shape[1]


def _pages(store: TileStore, cells: Array, width: int) -> tuple[Array, Array]:
    """Flat page index (within a page table) and offset in the tile of flat map cells
    ``cells`` [n, M] of a map ``width`` cells wide."""
    T, tx = _tile(store), store.page.shape[2]
    gi, gj = cells // width, cells % width
    return (gi // T) * tx + gj // T, (gi % T) * T + gj % T


def pool_index(store: TileStore, particles: Array, cells: Array, on_map: Array,
               width: int) -> Array:
    """Flat index into ``kpool.reshape(-1)`` of cell ``cells[i, m]`` of particle
    ``particles[i]`` (the page lookup and the cell's offset in one index); cells not on_map
    point at the zero sentinel's first cell."""
    T2 = _tile(store) ** 2
    pg, off = _pages(store, jnp.where(on_map, cells, 0), width)
    tiles = store.page.reshape(store.page.shape[0], -1)[particles[:, None], pg]
    P = store.refcount.shape[0]
    return jnp.where(on_map, tiles * T2 + off, P * T2)


def read(store: TileStore, particles: Array, cells: Array, on_map: Array,
         width: int) -> tuple[Array, Array]:
    """(k, S) [n, M] at flat map cells ``cells`` [n, M] of particles ``particles`` [n]; 0 where
    not on_map or never written."""
    idx = pool_index(store, particles, cells, on_map, width)

    def get(pool: Array) -> Array:
        return pool.reshape(-1).at[idx].get(mode="promise_in_bounds")

    return get(store.kpool), get(store.spool)


def known_bits(store: TileStore, particles: Array, map_shape: tuple[int, int]) -> Array:
    """Known-cell bitmasks [n, H/8, W/8, 2] of particles [n], laid out as the dense store's
    (``unknown.pack_known`` of the whole map), for ``unknown.sample_known_cells``."""
    H, W = map_shape
    b = store.bpool[store.page[particles]]  # [n, ty, tx, T/8, T/8, 2]
    n, ty, tx, nb = b.shape[:4]
    b = b.transpose(0, 1, 3, 2, 4, 5).reshape(n, ty * nb, tx * nb, 2)
    return b[:, :H // unknown.BLOCK, :W // unknown.BLOCK]


def _requests(store: TileStore, particles: Array, cells: Array, written: Array, width: int,
              window: int) -> tuple[Array, Array, Array]:
    """The pages each particle writes, as a [n, window**2] grid of candidate pages anchored at
    the smallest page row / column it writes: (flat page index [n, K], written [n, K], whether
    some written cell fell outside the grid)."""
    T, (ty, tx) = _tile(store), store.page.shape[1:]
    pi = jnp.where(written, (cells // width) // T, ty)
    pj = jnp.where(written, (cells % width) // T, tx)
    bi, bj = jnp.min(pi, axis=1), jnp.min(pj, axis=1)
    li, lj = pi - bi[:, None], pj - bj[:, None]
    inside = (li < window) & (lj < window)
    n, K = cells.shape[0], window * window
    local = jnp.where(written & inside, li * window + lj, K)
    flags = jnp.zeros((n, K), bool).at[jnp.arange(n)[:, None], local].set(True, mode="drop")
    gi = bi[:, None] + jnp.arange(K) // window
    gj = bj[:, None] + jnp.arange(K) % window
    flags &= (gi < ty) & (gj < tx)
    return jnp.where(flags, gi * tx + gj, 0), flags, jnp.any(written & ~inside)


def _keep_one_holder(cur: Array, shared: Array, refcount: Array) -> Array:
    """Of the requests on tiles with refcount > 1 (``shared``), the one per tile that may keep
    it because every holder of that tile is among the requests (the first in index order)."""
    big = jnp.iinfo(jnp.int32).max
    key = jnp.where(shared, cur, big)
    order = jnp.argsort(key, stable=True)
    s = key[order]
    count = jnp.searchsorted(s, s, side="right") - jnp.searchsorted(s, s, side="left")
    first = jnp.concatenate([jnp.ones((1,), bool), s[1:] != s[:-1]])
    keep_sorted = first & (s != big) & (count == refcount[jnp.minimum(s, refcount.shape[0] - 1)])
    return jnp.zeros_like(shared).at[order].set(keep_sorted)


def prepare(store: TileStore, particles: Array, cells: Array, written: Array, width: int,
            window: int) -> tuple[TileStore, Array, Array]:
    """Give every page that particles [n] write (``cells`` [n, M] where ``written``) a tile of
    their own: fresh, copied (copy-on-write) or kept. Returns the store, the tiles written
    [n * window**2] (P + 1 where none: out of range, for dropping scatters) and whether the
    pool had room (if not, nothing changed and the POOL_EXHAUSTED bit is set)."""
    P = store.refcount.shape[0]
    pg, need, outside = _requests(store, particles, cells, written, width, window)
    n, K = pg.shape
    rows = jnp.broadcast_to(particles[:, None], (n, K)).reshape(-1)
    pg, need = pg.reshape(-1), need.reshape(-1)
    flat_page = store.page.reshape(store.page.shape[0], -1)
    cur = jnp.where(need, flat_page[rows, pg], P)
    held = cur < P
    ref = store.refcount[jnp.minimum(cur, P - 1)]
    shared = need & held & (ref > 1)
    copy = shared & ~_keep_one_holder(cur, shared, store.refcount)
    alloc = (need & ~held) | copy
    m = jnp.sum(alloc, dtype=jnp.int32)
    ok = m <= store.n_free
    alloc &= ok
    rank = jnp.cumsum(alloc, dtype=jnp.int32) - 1
    new = jnp.where(alloc, store.free[jnp.clip(store.n_free - 1 - rank, 0, P - 1)], P + 1)
    kpool, spool = _copy_tiles(store.kpool, store.spool, jnp.where(copy, cur, P), new, alloc, m)
    target = jnp.where(alloc, new, cur)
    flat_page = flat_page.at[rows, jnp.where(alloc, pg, flat_page.shape[1])].set(new, mode="drop")
    refcount = store.refcount.at[new].set(1, mode="drop")
    refcount = refcount.at[jnp.where(copy & ok, cur, P)].add(-1, mode="drop")
    n_free = store.n_free - jnp.where(ok, m, 0)
    status = (store.status | jnp.where(ok, 0, POOL_EXHAUSTED)
              | jnp.where(outside, WINDOW_EXCEEDED, 0))
    store = store._replace(kpool=kpool, spool=spool, page=flat_page.reshape(store.page.shape),
                           refcount=refcount, n_free=n_free,
                           peak=jnp.maximum(store.peak, P - n_free), status=status)
    return store, jnp.where(need & ok, target, P + 1), ok


def _copy_tiles(kpool: Array, spool: Array, src: Array, dst: Array, alloc: Array,
                m: Array) -> tuple[Array, Array]:
    """pool[dst[r]] = pool[src[r]] for the ``m`` requests r with ``alloc`` (src P: the zero
    sentinel, i.e. a fresh tile), ``COPY_CHUNK`` tiles at a time."""
    R = src.shape[0]
    slots = jnp.nonzero(alloc, size=R, fill_value=R)[0]
    src = jnp.concatenate([src, jnp.array([0], src.dtype)])
    dst = jnp.concatenate([dst, jnp.array([kpool.shape[0]], dst.dtype)])
    chunks = -(-R // COPY_CHUNK)
    slots = jnp.pad(slots, (0, chunks * COPY_CHUNK - R), constant_values=R)

    def one(c, pools):
        take = lax.dynamic_slice_in_dim(slots, c * COPY_CHUNK, COPY_CHUNK)
        s, d = src[take], dst[take]
        return tuple(p.at[d].set(p[s], mode="drop") for p in pools)

    return lax.fori_loop(0, (m + COPY_CHUNK - 1) // COPY_CHUNK, one, (kpool, spool))


def add(store: TileStore, particles: Array, cells: Array, on_map: Array, k: Array, S: Array,
        width: int) -> TileStore:
    """maps[particles[i]][cells[i, m]] += (k[m], S[m]) (eq. 14) where on_map; call after
    ``prepare`` on the same cells, so that no shared tile is written (cells whose value is 0,
    e.g. padding, may land anywhere: adding 0 changes nothing)."""
    idx = pool_index(store, particles, cells, on_map, width)
    shape = idx.shape

    def put(pool, v):
        v = jnp.where(on_map, jnp.broadcast_to(v, shape), 0.0)
        return pool.reshape(-1).at[idx].add(v, mode="promise_in_bounds").reshape(pool.shape)

    return store._replace(kpool=put(store.kpool, k), spool=put(store.spool, S))


def _known_cells(k: Array) -> tuple[Array, Array]:
    """Known-cell bits [n, T/8, T/8, 2] of tiles k [n, T, T] and their counts per row of blocks
    [n, T/8] (``unknown.segment_counts`` with segments a tile wide)."""
    bits = jax.vmap(lambda t: unknown.pack_known(t > 0))(k)
    return bits, unknown.segment_counts(bits, bits.shape[-2])[..., 0]


def _refresh_bits(store: TileStore, tiles: Array) -> TileStore:
    """Known-cell bits and counts of the pool tiles ``tiles`` (P + 1: skip) recomputed from
    their k."""
    if store.bpool.shape[1] == 0:
        return store
    P = store.refcount.shape[0]
    bits, counts = _known_cells(store.kpool[jnp.minimum(tiles, P)])
    return store._replace(bpool=store.bpool.at[tiles].set(bits, mode="drop"),
                          cpool=store.cpool.at[tiles].set(counts, mode="drop"))


def write(store: TileStore, particles: Array, cells: Array, on_map: Array, k: Array, S: Array,
          width: int, window: int) -> TileStore:
    """Eq. 14 for particles [n]: ``prepare`` the pages of the observed cells (k > 0), add
    (k, S) at ``cells`` [n, M], refresh the written tiles' known-cell bits. If the pool ran
    out, nothing is written (and ``status`` says so)."""
    written = on_map & (jnp.broadcast_to(k, cells.shape) > 0)
    store, tiles, ok = prepare(store, particles, cells, written, width, window)
    store = add(store, particles, cells, on_map & ok, k, S, width)
    return _refresh_bits(store, tiles)


def resample(store: TileStore, ancestors: Array) -> TileStore:
    """Particle i takes the map of particle ancestors[i]: the page tables are gathered, the
    references recounted, and tiles no page points at any more return to the free stack."""
    P = store.refcount.shape[0]
    page = store.page[ancestors]
    refcount = jnp.zeros((P + 1,), jnp.int32).at[page.reshape(-1)].add(1)[:P]
    unused = refcount == 0
    free = jnp.nonzero(unused, size=P, fill_value=0)[0].astype(jnp.int32)
    return store._replace(page=page, refcount=refcount, free=free,
                          n_free=jnp.sum(unused, dtype=jnp.int32))


def grow(store: TileStore, pool_tiles: int) -> TileStore:
    """The same maps in a pool of ``pool_tiles`` tiles (at least the present pool's): the new
    tiles go on the free stack, below the tiles already free, and the zero sentinel moves to
    the new end (unwritten pages follow it). Every tile keeps its index and contents, so
    ``to_dense`` is unchanged, and so is every later read and write's value."""
    P, new = store.refcount.shape[0], int(pool_tiles)
    T = _tile(store)
    if new < P:
        raise ValueError(f"pool_tiles {new}: a pool cannot shrink (it has {P} tiles)")
    if (new + 1) * T * T >= 2 ** 31:
        raise ValueError(f"pool_tiles {new} of {T} x {T} cells exceeds the int32 cell index")
    if new == P:
        return store
    extra = new - P

    def pool(x: Array) -> Array:  # tiles 0 .. P-1, the new ones (zero), the sentinel
        return jnp.concatenate([x[:P], jnp.zeros((extra,) + x.shape[1:], x.dtype), x[P:]])

    # free[:n_free] is a stack popped from the top: the new tiles go under the old free ones
    free = jnp.concatenate([jnp.arange(P, new, dtype=jnp.int32), store.free])
    return store._replace(
        kpool=pool(store.kpool), spool=pool(store.spool), bpool=pool(store.bpool),
        cpool=pool(store.cpool),
        page=jnp.where(store.page == P, new, store.page),
        refcount=jnp.concatenate([store.refcount, jnp.zeros((extra,), jnp.int32)]),
        free=free, n_free=store.n_free + extra)


def to_dense(store: TileStore, map_shape: tuple[int, int]) -> tuple[Array, Array, Array]:
    """The dense store's arrays: k, S [J, H, W] and known bits [J, H/8, W/8, 2] (the last
    [J, 0, 0, 2] when bits are not kept)."""
    H, W = map_shape
    J, ty, tx = store.page.shape
    T = _tile(store)

    def unpack(pool):
        x = pool[store.page]  # [J, ty, tx, T, T]
        return x.transpose(0, 1, 3, 2, 4).reshape(J, ty * T, tx * T)[:, :H, :W]

    if store.bpool.shape[1]:
        bits = known_bits(store, jnp.arange(J), map_shape)
    else:
        bits = jnp.zeros((J, 0, 0, 2), jnp.uint32)
    return unpack(store.kpool), unpack(store.spool), bits


def live_tiles(store: TileStore) -> Array:
    """Tiles held by some page now."""
    return store.refcount.shape[0] - store.n_free
