"""Window map store: each particle's map kept as its path over the shared local maps, with only
the cells near the particle materialised (issue 67, docs/particle-budget.md).

A particle's map is a function of its path and of the local maps, which every particle shares:
cell c of particle j's map is the sum, over the updates u so far, of the local map of u
scattered from j's pose at u (eq. 14). The dense store keeps that sum for every cell, so its
memory is J x the area; this store keeps

* the local maps once for all particles (their observed cells, ``Observation``), ``U`` of them;
* each particle's pose at each update (its ancestral path: resampling copies it with the map);
* for each particle a C x C window of (k, S) around it, addressed toroidally: global cell
  (i, j) lives in slot (i mod C, j mod C) while it lies in the particle's window
  [origin, origin + C)^2. Every cell in the window holds the particle's full sum.

so memory is J x (C^2 + path) plus the local maps, whatever the area. A window holds the
footprint of a particle within ``step`` cells of its safe range (``_safe``), which is 2 step
cells wide; after each update (``finish_update``) the windows of the particles that left it
move (``_move``: in jumps of at least a step, so most updates move few windows, and only
those are visited), and the cells that enter them are zeroed and refilled by replaying, in
update order, the past local maps whose box of written cells meets them, from the particle's
pose at each, with the placement the update used (``placement.observation_cells``): the same
additions in the same order as the dense map's, so the values are the dense store's. A
written cell outside the window (a particle that moved more than ``step`` cells) sets
``MISSED`` (an error on the host).

Only eq. 30 (``unknown_cells = "ignore"``) and maps that start empty: eq. 31 draws known
cells uniformly from the whole map, which this store does not hold (``rbpf.maps`` refuses
both with a ConfigError).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array, lax

from gslam_jax.rbpf.densestore import gather_particles
from gslam_jax.rbpf.placement import observation_cells, observation_rows_cols
from gslam_jax.rbpf.types import FilterConfig, Observation

__all__ = ["WindowMaps", "MISSED", "HISTORY_FULL", "REFILL_OVERFLOW", "UNSET", "observed_reach",
           "reach", "groups", "chunk", "side",
           "init", "nbytes", "grow_history", "read", "write", "finish_update", "resample",
           "to_dense", "particle_map"]

MISSED = 1           # status bit: an update wrote a map cell outside the particle's window
HISTORY_FULL = 2     # status bit: more updates than the history holds (``history``)
REFILL_OVERFLOW = 4  # status bit: cells entering a window met more past local maps than ``replays``
UNSET = -(2 ** 30)   # origin of a window no update has placed yet (its map is empty)


class WindowMaps(NamedTuple):
    """The maps of J particles as paths over U shared local maps plus a C x C window each."""

    k: Array          # [J, C, C] float32 window of k, toroidal (global (i, j) at (i % C, j % C))
    S: Array          # [J, C, C] float32 window of S
    origin: Array     # [J, 2] int32 global cell of the window's first row and column (UNSET)
    path: Array       # [J, U, 3] float32 each particle's pose at each update so far
    obs_index: Array  # [U, M] int32 flat local cell of each observed cell of each update
    obs_k: Array      # [U, M] float32 its k (0: padding)
    obs_S: Array      # [U, M] float32 its S
    obs_heading: Array  # [U] float32 the local map's lattice heading
    obs_box: Array    # [U, G, 4] float32 the box of the written cells of each group (``_extent``)
    count: Array      # [] int32 updates recorded
    status: Array     # [] int32 sticky error bits (MISSED | HISTORY_FULL | REFILL_OVERFLOW)


def observed_reach(local_maps) -> int:
    """Cells from a particle's cell to the farthest map cell the observed cells (k > 0) of
    ``local_maps`` [n, L, L, 2] (host arrays) can land in: the farthest observed cell centre
    from the local map's centre, rounded up, plus one for the particle's own cell (as
    ``FilterConfig.reach`` for the whole local map); 0 when nothing is observed."""
    k = np.asarray(local_maps)[..., 0]
    if k.size == 0 or not np.any(k > 0):
        return 0
    L = k.shape[-1]
    seen = np.any(k > 0, axis=0)
    centre = np.arange(L) - L // 2 + 0.5
    d = np.hypot(centre[:, None], centre[None, :])
    return int(math.ceil(float(np.max(d[seen])))) + 1


def reach(cfg: FilterConfig) -> int:
    """Cells from a particle's cell to the farthest cell its update writes: the run's
    ``observed_reach`` where sized, else the local map's diagonal (``FilterConfig.reach``)."""
    return cfg.observed_reach or cfg.reach


def side(cfg: FilterConfig) -> int:
    """C: window side in cells, 2 (reach + step) + slack rounded up to a multiple of 8, where
    ``reach`` is ``reach(cfg)``, ``step`` (``cfg.tile``) how far the particle may move between
    updates, and the slack (2 step) how far it may drift before its window moves
    (``_move``)."""
    return -(-(2 * (reach(cfg) + cfg.tile) + 2 * cfg.tile) // 8) * 8


def groups(M: int) -> int:
    """G: the groups of consecutive observed cells (local rows, in the local map's row-major
    order) a local map is replayed by: the most of 16, 8, 4, 2 that divides M, else 1."""
    return next(g for g in (16, 8, 4, 2, 1) if M % g == 0)


def history(cfg: FilterConfig) -> int:
    """U: updates the history holds (``cfg.pool_tiles``; 0 is resolved from the run before,
    ``maps.resolve_history``)."""
    return max(cfg.pool_tiles, 1)


def init(cfg: FilterConfig) -> WindowMaps:
    """J empty maps: no update recorded, every window unplaced (``UNSET``)."""
    J, C, U, M = cfg.num_particles, side(cfg), history(cfg), cfg.max_observed
    if J * C * C >= 2 ** 31:
        raise ValueError(f"{J} windows of {C} x {C} cells exceed the int32 cell index")
    return WindowMaps(k=jnp.zeros((J, C, C), jnp.float32), S=jnp.zeros((J, C, C), jnp.float32),
                      origin=jnp.full((J, 2), UNSET, jnp.int32),
                      path=jnp.zeros((J, U, 3), jnp.float32),
                      obs_index=jnp.zeros((U, M), jnp.int32),
                      obs_k=jnp.zeros((U, M), jnp.float32), obs_S=jnp.zeros((U, M), jnp.float32),
                      obs_heading=jnp.zeros((U,), jnp.float32),
                      obs_box=jnp.zeros((U, groups(M), 4), jnp.float32), count=jnp.int32(0),
                      status=jnp.int32(0))


def nbytes(cfg: FilterConfig) -> int:
    """Bytes ``init`` allocates: J windows of k and S, J paths of U poses, U local maps (their
    cells, heading and groups' boxes)."""
    J, C, U, M = cfg.num_particles, side(cfg), history(cfg), cfg.max_observed
    return J * (C * C * 8 + 8 + U * 12) + U * (M * 12 + 4 + groups(M) * 16) + 8


def grow_history(store: WindowMaps, updates: int) -> WindowMaps:
    """``store`` with room for ``updates`` local maps in its history (at least the U it has):
    the paths and local maps recorded so far kept, the rest empty. Changes no map."""
    grow = updates - store.obs_k.shape[0]
    if grow < 0:
        raise ValueError(f"grow_history: {updates} updates is fewer than the "
                         f"{store.obs_k.shape[0]} the history holds")

    def pad(x: Array, axis: int) -> Array:
        widths = [(0, 0)] * x.ndim
        widths[axis] = (0, grow)
        return jnp.pad(x, widths)

    return store._replace(path=pad(store.path, 1), obs_index=pad(store.obs_index, 0),
                          obs_k=pad(store.obs_k, 0), obs_S=pad(store.obs_S, 0),
                          obs_heading=pad(store.obs_heading, 0), obs_box=pad(store.obs_box, 0))


def _slots(store: WindowMaps, rows: Array, cells_: Array, width: int
           ) -> tuple[Array, Array]:
    """Flat index into ``k.reshape(-1)`` of flat map cells ``cells_`` [n, M] of particles
    ``rows`` [n] and whether each lies in its particle's window."""
    C = store.k.shape[1]
    # cells_ >= 0: truncating division is floor division, without its sign fix-ups
    gi, gj = lax.div(cells_, jnp.int32(width)), lax.rem(cells_, jnp.int32(width))
    o = store.origin[rows]
    slot, inside = _window_slot(gi, gj, o[:, :1], o[:, 1:], C)
    return jnp.where(inside, rows[:, None] * (C * C) + slot, 0), inside


def _window_slot(gi: Array, gj: Array, oi: Array, oj: Array, C: int) -> tuple[Array, Array]:
    """Slot (row * C + column) in a C x C toroidal window with origin (oi, oj) of global cells
    (gi, gj), and whether each lies in the window [oi, oi + C) x [oj, oj + C). The origin's
    slot is taken modulo C once; a cell's is that plus its offset, less C past the end (no
    division per cell)."""
    di, dj = gi - oi, gj - oj  # in [0, C) inside the window
    inside = (di >= 0) & (di < C) & (dj >= 0) & (dj < C)
    si, sj = jnp.remainder(oi, C) + di, jnp.remainder(oj, C) + dj
    return jnp.where(si >= C, si - C, si) * C + jnp.where(sj >= C, sj - C, sj), inside


def read(store: WindowMaps, rows: Array, cells_: Array, on_map: Array, width: int
         ) -> tuple[Array, Array]:
    """(k, S) [n, M] at flat map cells ``cells_`` [n, M] of particles ``rows`` [n]; 0 where
    not on_map or outside the window (a written cell there sets ``MISSED`` in ``write``)."""
    idx, inside = _slots(store, rows, cells_, width)
    use = on_map & inside

    def get(x: Array) -> Array:
        return jnp.where(use, x.reshape(-1).at[idx].get(mode="promise_in_bounds"), 0.0)

    return get(store.k), get(store.S)


def _placed(store: WindowMaps, rows: Array, cells_: Array, written: Array, width: int
            ) -> WindowMaps:
    """Windows of particles ``rows`` not yet placed, centred on the bounding box of their
    written cells (their maps are empty, so any place is exact). Where every window is placed
    (every update after a particle's first that wrote), the cells are not looked at."""
    C = store.k.shape[1]
    big = jnp.iinfo(jnp.int32).max
    o = store.origin[rows]

    def fresh() -> Array:
        gi, gj = cells_ // width, cells_ % width

        def centre(g: Array) -> Array:
            lo = jnp.min(jnp.where(written, g, big), axis=1)
            hi = jnp.max(jnp.where(written, g, -1), axis=1)
            return jnp.where(hi >= 0, (lo + hi) // 2 - C // 2, UNSET)

        return jnp.where(o == UNSET, jnp.stack([centre(gi), centre(gj)], axis=1), o)

    new = lax.cond(jnp.any(o == UNSET), fresh, lambda: o)
    return store._replace(origin=store.origin.at[rows].set(new))


def write(store: WindowMaps, rows: Array, cells_: Array, k: Array, S: Array,
          map_shape: tuple[int, int]) -> WindowMaps:
    """Eq. 14: add (k, S) [M] at flat map cells ``cells_`` [n, M] (H*W: off the map) of
    particles ``rows`` [n], in their windows (placed first where unplaced). A written cell
    (k > 0) on the map but outside the window sets ``MISSED``."""
    H, W = map_shape
    on_map = cells_ < H * W
    written = on_map & (jnp.broadcast_to(k, cells_.shape) > 0)
    store = _placed(store, rows, jnp.where(on_map, cells_, 0), written, W)
    idx, inside = _slots(store, rows, jnp.where(on_map, cells_, 0), W)
    use = on_map & inside

    def put(x: Array, v: Array) -> Array:
        v = jnp.where(use, jnp.broadcast_to(v, idx.shape), 0.0)
        return x.reshape(-1).at[idx].add(v, mode="promise_in_bounds").reshape(x.shape)

    missed = jnp.any(written & ~inside)
    return store._replace(k=put(store.k, k), S=put(store.S, S),
                          status=store.status | jnp.where(missed, MISSED, 0))


def _record(store: WindowMaps, pose: Array, obs: Observation, cfg: FilterConfig
            ) -> WindowMaps:
    """The update just written appended to the history: its local map (and the box of its
    written cells' groups, ``_extent``) and every pose."""
    U = store.obs_k.shape[0]
    u = jnp.minimum(store.count, U - 1)
    full = store.count >= U
    keep = lambda new, old: jnp.where(full, old, new)  # noqa: E731
    return store._replace(
        path=store.path.at[:, u].set(keep(pose, store.path[:, u])),
        obs_index=store.obs_index.at[u].set(keep(obs.index, store.obs_index[u])),
        obs_k=store.obs_k.at[u].set(keep(obs.k, store.obs_k[u])),
        obs_S=store.obs_S.at[u].set(keep(obs.S, store.obs_S[u])),
        obs_box=store.obs_box.at[u].set(keep(_extent(obs, cfg.local_size,
                                                     store.obs_box.shape[1]),
                                             store.obs_box[u])),
        obs_heading=store.obs_heading.at[u].set(
            keep(jnp.asarray(obs.lattice_heading, jnp.float32), store.obs_heading[u])),
        count=jnp.minimum(store.count + 1, U),
        status=store.status | jnp.where(full, HISTORY_FULL, 0))


def _entered(old: Array, new: Array, C: int) -> tuple[Array, Array]:
    """[lo, hi) global rows (or columns) that a window moving from ``old`` to ``new`` takes in."""
    return jnp.where(new > old, old + C, new), jnp.where(new > old, new + C, old)


class _Move(NamedTuple):
    """Windows' moves: the new origins, and the rows and columns each takes in."""

    origin: Array  # [..., 2]
    rows: Array    # [..., 2] [lo, hi)
    cols: Array    # [..., 2] [lo, hi)


def _safe(C: int, cfg: FilterConfig) -> tuple[int, int]:
    """[lo, hi]: the particle's cell less its window's origin, per axis, from which a move of
    up to ``step`` cells keeps the next footprint (``reach`` around it) in the window."""
    return reach(cfg) + cfg.tile, C - 1 - reach(cfg) - cfg.tile


def _jump(C: int, cfg: FilterConfig) -> int:
    """The most cells a window moves an axis in one update: from a particle ``step`` cells past
    one end of the safe range to a quarter of the range from the other (``_move``)."""
    lo, hi = _safe(C, cfg)
    return hi - lo + cfg.tile


def _move(origin: Array, pose: Array, C: int, cfg: FilterConfig) -> _Move:
    """The window of a particle that left its safe range (``_safe``) moved so that the
    particle sits a quarter of the range from the other end (it has three quarters of the
    range ahead, in the direction it left by, before the window moves again); otherwise it
    stays. Moves are clipped to
    ``_jump`` (a particle that moved more than ``step`` cells is reported by ``write``)."""
    cell = jnp.floor((pose[:2] - jnp.asarray(cfg.map_origin, jnp.float32))
                     / cfg.resolution)
    cell = jnp.clip(jnp.nan_to_num(cell), -2 ** 24, 2 ** 24).astype(jnp.int32)
    lo, hi = _safe(C, cfg)
    lead = (hi - lo) // 4
    f = cell - origin
    f_new = jnp.where(f > hi, lo + lead, jnp.where(f < lo, hi - lead, f))
    jump = jnp.clip(f - f_new, -_jump(C, cfg), _jump(C, cfg))
    new = jnp.where(origin == UNSET, origin, origin + jump)
    r0, r1 = _entered(origin[0], new[0], C)
    c0, c1 = _entered(origin[1], new[1], C)
    return _Move(new, jnp.stack([r0, r1]), jnp.stack([c0, c1]))


def _extent(obs: Observation, L: int, G: int) -> Array:
    """[G, 4] float32 for each of G groups of a local map's consecutive observed cells, the box
    (a_lo, a_hi, b_lo, b_hi) of the centres of its written cells (k or S nonzero), in cells
    from the local map's centre, as ``observation_cells`` places them; a_lo > a_hi where the
    group wrote nothing."""
    used = ((obs.k != 0) | (obs.S != 0)).reshape(G, -1)
    index = obs.index.reshape(G, -1)
    ca = (index // L).astype(jnp.float32) - (L // 2) + 0.5
    cb = (index % L).astype(jnp.float32) - (L // 2) + 0.5
    big = jnp.float32(L)
    return jnp.stack([jnp.min(jnp.where(used, ca, big), axis=1),
                      jnp.max(jnp.where(used, ca, -big), axis=1),
                      jnp.min(jnp.where(used, cb, big), axis=1),
                      jnp.max(jnp.where(used, cb, -big), axis=1)], axis=1)


def _meets(a0: Array, a1: Array, b0: Array, b1: Array) -> Array:
    """Whether the half-open ranges [a0, a1) and [b0, b1) overlap."""
    return (a0 < b1) & (b0 < a1)


def _enters(lo_i: Array, hi_i: Array, lo_j: Array, hi_j: Array, mv: _Move, C: int) -> Array:
    """Whether boxes of map cells [lo_i, hi_i) x [lo_j, hi_j) meet the cells a window takes in
    (``mv``): its entering rows within its columns, or its entering columns within its rows."""
    o = mv.origin
    in_rows = _meets(lo_i, hi_i, o[0], o[0] + C)
    in_cols = _meets(lo_j, hi_j, o[1], o[1] + C)
    new_rows = _meets(lo_i, hi_i, mv.rows[0], mv.rows[1]) & (mv.rows[1] > mv.rows[0])
    new_cols = _meets(lo_j, hi_j, mv.cols[0], mv.cols[1]) & (mv.cols[1] > mv.cols[0])
    return (new_rows & in_cols) | (new_cols & in_rows)


def _map_cell(x: Array) -> Array:
    """Map cell (row or column) of a position in cells, clipped into int32 (NaN: 0)."""
    return jnp.clip(jnp.nan_to_num(jnp.floor(x)), -2 ** 24, 2 ** 24).astype(jnp.int32)


def _near(path: Array, recorded: Array, mv: _Move, C: int, cfg: FilterConfig) -> Array:
    """[U] the past local maps of one particle that may land in the cells its window takes in,
    by a test without the heading: every observed cell of a local map lands within ``reach``
    cells of the particle's cell at that update, so a square of that half-side around it
    holds all of them. Every map with a cell that can land there passes; a map that ``_hits``
    keeps only because a group's box (wider than its cells) reaches the band may not."""
    r = reach(cfg) + 1
    i = _map_cell((path[:, 0] - cfg.map_origin[0]) / cfg.resolution)
    j = _map_cell((path[:, 1] - cfg.map_origin[1]) / cfg.resolution)
    return recorded & _enters(i - r, i + r + 1, j - r, j + r + 1, mv, C)


def _hits(path: Array, recorded: Array, box: Array, heading: Array, mv: _Move, C: int,
          cfg: FilterConfig) -> Array:
    """[U, G] the groups of U past local maps (``recorded`` [U]: those that hold one) of one
    particle whose written cells may land in the cells its window takes in: each group's box
    of written cells (``_extent``) turned by the particle's heading at that update, its
    bounding box in map cells widened by a cell for rounding (``observation_cells``' floor),
    against the window and the entering band."""
    px = ((path[:, 0] - cfg.map_origin[0]) / cfg.resolution)[:, None]
    py = ((path[:, 1] - cfg.map_origin[1]) / cfg.resolution)[:, None]
    t = (path[:, 2] + heading)[:, None]
    c, s = jnp.cos(t), jnp.sin(t)
    ma, mb = 0.5 * (box[..., 0] + box[..., 1]), 0.5 * (box[..., 2] + box[..., 3])
    ha, hb = 0.5 * (box[..., 1] - box[..., 0]), 0.5 * (box[..., 3] - box[..., 2])
    ci, cj = px + c * ma - s * mb, py + s * ma + c * mb
    ei, ej = jnp.abs(c) * ha + jnp.abs(s) * hb, jnp.abs(s) * ha + jnp.abs(c) * hb
    lo_i, hi_i = _map_cell(ci - ei) - 1, _map_cell(ci + ei) + 2  # [lo, hi) map rows
    lo_j, hi_j = _map_cell(cj - ej) - 1, _map_cell(cj + ej) + 2
    wrote = box[..., 0] <= box[..., 1]
    return recorded[:, None] & wrote & _enters(lo_i, hi_i, lo_j, hi_j, mv, C)


def _zero_entered(x: Array, ids: Array, mv: _Move, width: int) -> Array:
    """x [J, C, C] with the slots of the rows and columns that the windows of particles
    ``ids`` [P] (J: none) take in (``mv``, at most ``width`` of each) zeroed."""
    J, C = x.shape[0], x.shape[1]
    t = jnp.arange(width)

    def slots(band):  # [P, width] slots of global rows (or columns) [lo, hi); C: none
        g = band[:, :1] + t
        return jnp.where((g < band[:, 1:]) & (ids[:, None] < J), g % C, C)

    rows = jnp.where(slots(mv.rows) < C, ids[:, None] * C + slots(mv.rows), J * C)
    x = x.reshape(J * C, C).at[rows].set(0.0, mode="drop").reshape(J, C, C)
    return x.at[ids[:, None], :, slots(mv.cols)].set(0.0, mode="drop")


def _replay_slots(pose: Array, index: Array, mv: _Move, C: int, cfg: FilterConfig,
                  heading: Array) -> Array:
    """Window slot (C * C: none) of each of the cells ``index`` of a past local map seen from
    ``pose`` that lands in the cells the window took in (``mv``), placed as the update placed
    them."""
    H, W = cfg.map_shape
    gi, gj = observation_rows_cols(pose, index, cfg, heading)
    on_map = (gi >= 0) & (gi < H) & (gj >= 0) & (gj < W)
    slot, inside = _window_slot(gi, gj, mv.origin[0], mv.origin[1], C)
    entered = (((gi >= mv.rows[0]) & (gi < mv.rows[1]))
               | ((gj >= mv.cols[0]) & (gj < mv.cols[1])))
    return jnp.where(on_map & inside & entered, slot, C * C)


def _refill(store: WindowMaps, k: Array, S: Array, ids: Array, mv: _Move, cfg: FilterConfig,
            R: int) -> tuple[Array, Array, Array]:
    """k, S [J, C, C] with the cells that the windows of particles ``ids`` [P] (J: none) took
    in refilled from the groups of past local maps that may land there (``_hits``), each
    particle's in update order and within an update in cell order, with the update's own
    placement: the dense store's additions in its order. G groups are replayed per particle
    per pass. Also whether a particle met more than ``R`` past local maps."""
    J, C = k.shape[0], k.shape[1]
    U, G = store.obs_box.shape[:2]
    n = store.obs_k.shape[1] // G
    live = ids < J
    idc = jnp.minimum(ids, J - 1)
    path = store.path[idc]
    which, pair_hit, n_maps = _selected(store, path, live, mv, C, cfg, R)
    pair_hit = pair_hit.reshape(-1, R * G)
    pairs = jax.vmap(lambda h: jnp.nonzero(h, size=R * G, fill_value=R * G)[0])(pair_hit)
    n_pairs = jnp.sum(pair_hit, axis=1)
    pairs = jnp.concatenate([pairs, jnp.full((pairs.shape[0], G), R * G, pairs.dtype)], 1)
    index = store.obs_index.reshape(U, G, n)
    ok, oS = store.obs_k.reshape(U, G, n), store.obs_S.reshape(U, G, n)

    def one(r, kS):
        k, S = kS
        q = lax.dynamic_slice_in_dim(pairs, r * G, G, axis=1)  # [P, G] in order
        live_q = q < R * G
        u = jnp.take_along_axis(which, jnp.minimum(q, R * G - 1) // G, axis=1)
        u = jnp.where(live_q, jnp.minimum(u, U - 1), 0)
        g = jnp.where(live_q, q % G, 0)
        pose = jax.vmap(lambda p, uu: p[uu])(path, u)  # [P, G, 3]
        slot = jax.vmap(jax.vmap(lambda p, u1, g1, m: _replay_slots(
            p, index[u1, g1], m, C, cfg, store.obs_heading[u1]), in_axes=(0, 0, 0, None)))(
                pose, u, g, mv)  # [P, G, n]
        use = (slot < C * C) & live_q[:, :, None]
        flat = jnp.where(use, ids[:, None, None] * (C * C) + slot, J * C * C).reshape(-1)

        def put(x, v):
            return x.reshape(-1).at[flat].add(v[u, g].reshape(-1), mode="drop").reshape(x.shape)

        return put(k, ok), put(S, oS)

    k, S = lax.fori_loop(0, (jnp.max(n_pairs) + G - 1) // G, one, (k, S))
    return k, S, jnp.any(n_maps > R)


def _selected(store: WindowMaps, path: Array, live: Array, mv: _Move, C: int,
              cfg: FilterConfig, R: int) -> tuple[Array, Array, Array]:
    """For particles with paths ``path`` [P, U, 3] (``live`` [P]) whose windows move by ``mv``:
    the first R past local maps in update order that have groups to replay (``_hits``), as
    (which [P, R] update indices, U: none; hit [P, R, G] their groups; n [P] how many there
    are in all). The groups are tested only for the maps ``_near`` keeps, up to R of them;
    where a particle has more than R near, all U maps are tested. Either way the replayed
    cells are the same (a map ``_near`` drops lands none in the band), though n may count
    fewer maps than the search of all U."""
    U = store.obs_box.shape[0]
    recorded = jnp.arange(U) < store.count

    def choose(h: Array, valid: Array) -> tuple[Array, Array, Array]:  # [P, V, G] -> R maps
        maps_hit = jnp.any(h, axis=2)
        pick = jax.vmap(lambda m: jnp.nonzero(m, size=R, fill_value=h.shape[1])[0])(maps_hit)
        some = pick < h.shape[1]
        pick = jnp.minimum(pick, h.shape[1] - 1)
        hit = jnp.take_along_axis(h, pick[:, :, None], axis=1) & some[:, :, None]
        return (jnp.where(some, jnp.take_along_axis(valid, pick, axis=1), U), hit,
                jnp.sum(maps_hit, axis=1))

    near = jax.vmap(lambda p, m: _near(p, recorded, m, C, cfg))(path, mv) & live[:, None]

    def by_candidates(_):
        cand = jax.vmap(lambda m: jnp.nonzero(m, size=R, fill_value=U)[0])(near)  # [P, R]
        u = jnp.minimum(cand, U - 1)
        h = jax.vmap(lambda p, u1, c, m: _hits(p[u1], c < U, store.obs_box[u1],
                                               store.obs_heading[u1], m, C, cfg))(
            path, u, cand, mv)
        return choose(h, cand)

    def by_all(_):
        h = jax.vmap(lambda p, m: _hits(p, recorded, store.obs_box, store.obs_heading, m, C,
                                        cfg))(path, mv) & live[:, None, None]
        return choose(h, jnp.broadcast_to(jnp.arange(U), (path.shape[0], U)))

    return lax.cond(jnp.max(jnp.sum(near, axis=1)) > R, by_all, by_candidates, None)


def chunk(J: int) -> int:
    """Particles whose windows move handled per pass of ``finish_update``."""
    return max(1, -(-J // 8))


def finish_update(store: WindowMaps, pose: Array, obs: Observation, cfg: FilterConfig,
                  replays: int = 128) -> WindowMaps:
    """After an update from ``pose`` [J, 3] with the local map ``obs`` wrote the maps: the
    update recorded; the windows of the particles that left their safe range moved
    (``_move``), the cells they take in zeroed and refilled from the past local maps whose
    footprint meets them, in update order (``_refill``; the dense store's additions in its
    order). Only the particles whose windows move are visited, ``chunk(J)`` at a time. A
    particle whose new cells meet more than ``replays`` past local maps sets
    ``REFILL_OVERFLOW``."""
    J, C = store.k.shape[0], store.k.shape[1]
    store = _record(store, pose, obs, cfg)
    moves = jax.vmap(lambda o, p: _move(o, p, C, cfg))(store.origin, pose)
    moved = jnp.any(moves.origin != store.origin, axis=1)
    P = chunk(J)
    n_chunks = -(-J // P)
    order = jnp.nonzero(moved, size=n_chunks * P, fill_value=J)[0]  # movers first, then J
    R = min(replays, store.obs_k.shape[0])

    def one(c, carry):
        k, S, overflow = carry
        ids = lax.dynamic_slice(order, (c * P,), (P,))
        mv = jax.tree_util.tree_map(lambda x: x[jnp.minimum(ids, J - 1)], moves)
        k = _zero_entered(k, ids, mv, _jump(C, cfg))
        S = _zero_entered(S, ids, mv, _jump(C, cfg))
        k, S, over = _refill(store, k, S, ids, mv, cfg, R)
        return k, S, overflow | over

    n_moved = jnp.sum(moved)
    k, S, overflow = lax.fori_loop(0, (n_moved + P - 1) // P, one,
                                   (store.k, store.S, jnp.bool_(False)))
    return store._replace(k=k, S=S, origin=moves.origin,
                          status=store.status | jnp.where(overflow, REFILL_OVERFLOW, 0))


def resample(store: WindowMaps, ancestors: Array) -> WindowMaps:
    """Particle i takes the map of particle ancestors[i] (survivors kept in place,
    ``resampling.keep_in_place``): its window, the window's origin and its path, copied into
    the slots of the particles left without offspring (``densestore.gather_particles``)."""
    k, S, origin, path = gather_particles((store.k, store.S, store.origin, store.path),
                                          ancestors)
    return store._replace(k=k, S=S, origin=origin, path=path)


def particle_map(store: WindowMaps, j: Array | int, cfg: FilterConfig) -> tuple[Array, Array]:
    """(k, S) [H, W] of particle ``j``'s whole map: every recorded local map replayed from
    its pose, in update order (eq. 14, as the dense store adds them)."""
    H, W = cfg.map_shape
    path = store.path[jnp.asarray(j)]

    def one(u, kS):
        k, S = kS
        flat, on_map = observation_cells(path[u], store.obs_index[u], cfg, store.obs_heading[u])
        idx = jnp.where(on_map, flat, 0)
        return (k.at[idx].add(jnp.where(on_map, store.obs_k[u], 0.0), mode="promise_in_bounds"),
                S.at[idx].add(jnp.where(on_map, store.obs_S[u], 0.0), mode="promise_in_bounds"))

    zero = jnp.zeros((H * W,), jnp.float32)
    k, S = lax.fori_loop(0, store.count, one, (zero, zero))
    return k.reshape(H, W), S.reshape(H, W)


def to_dense(store: WindowMaps, cfg: FilterConfig) -> tuple[Array, Array, Array]:
    """Every particle's whole map: k, S [J, H, W] (``particle_map``) and no known-cell bits
    ([J, 0, 0, 2]: "ignore" mode only)."""
    J = store.k.shape[0]
    k, S = lax.map(lambda j: particle_map(store, j, cfg), jnp.arange(J))
    return k, S, jnp.zeros((J, 0, 0, 2), jnp.uint32)
