"""The Gamma-SLAM Rao-Blackwellized particle filter on dense per-particle maps (paper 6.1-6.2).

Every particle carries a pose and a dense variance grid map stored as (k, S) arrays [J, H, W]
(``cells``). One frame of the filter is:

* ``predict`` at every frame: sample the motion model (eqs. 1-3, 24).
* ``update`` at frames that carry a local map: for each particle, every local cell's centre is
  rotated and translated into its global map (``observation_cells``); the log-gamma importance
  factors of the observed cells against the map cells under them (eq. 26) and their tempered
  combination (eq. 30 or 31) are one fused computation over the local map's M observed cells
  (``compact_observation``), in blocks of particles sized for the cache on a CPU
  (``FilterConfig.update_block``); the local map is then scatter-added into each particle's
  map (the conjugate update, eq. 14); the weights are
  multiplied (eq. 27) and normalised; the particles are resampled when the ESS (eq. 23) drops
  below ``resample_ratio * J``.

The whole Run is a ``lax.scan`` over frames (``run_filter``); poses and resampling ancestors are
kept per frame so the best particle's full path survives resampling (``backtrack_path``).
Random numbers come from ``motion_noise`` and ``update_noise`` so that another implementation
can be driven with exactly the same draws.
"""

from __future__ import annotations

import math
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array, lax

from gslam_jax import cells, resampling, unknown
from gslam_jax.motion import MotionParams, apply_motion

__all__ = ["FilterConfig", "FilterParams", "FilterState", "UpdateNoise", "StepInfo", "RunOutput",
           "init", "predict", "update", "step", "scan_frames", "frame_keys", "run_filter",
           "backtrack_path", "motion_noise", "update_noise", "window_origin", "gather_particles",
           "written_rows", "Observation", "compact_observation", "observation_cells",
           "log_importance", "best_slot"]

UNKNOWN_MODES = ("ignore", "sample")
CPU_BLOCK_CELLS = 102_400  # footprint cells per update pass on CPU (FilterConfig.update_block)


class FilterConfig(NamedTuple):
    """Static settings: shapes and discrete choices (hashable, a jit static argument).

    map_origin is the world (x, y) of the corner of cell (0, 0); cell (i, j) covers
    x in [x0 + i res, x0 + (i+1) res), y likewise with j. map_shape entries are multiples of 8.
    """

    num_particles: int
    map_shape: tuple[int, int]
    map_origin: tuple[float, float]
    resolution: float
    local_size: int
    resampler: str = "multinomial"
    resample_ratio: float = 0.5
    unknown_cells: str = "sample"
    unknown_samples: int = 1024
    update_map: bool = True
    observed_cells: int = 0
    particle_block: int = 0

    @property
    def update_block(self) -> int:
        """Particles per pass of the update's read-weigh-write (``particle_block``; 0: auto).

        Each pass reads a block's footprints, weighs them (eq. 26) and adds the local map to
        them (eq. 14) while they are still in cache. Auto: on a CPU, blocks of about
        ``CPU_BLOCK_CELLS`` footprint cells (25 particles of a 64 x 64 local map: 34-36 us per
        particle against 57-60 for one pass over J = 200, A/B in one process); on
        accelerators, one pass over all particles (the device wants them all at once). Auto
        reads the default backend when the update is traced; JAX may reuse that trace on
        another backend in the same process, so set ``particle_block`` there (the block size
        changes the speed; the results agree to float rounding).
        """
        J = self.num_particles
        if self.particle_block:
            return min(self.particle_block, J)
        if jax.default_backend() != "cpu":
            return J
        return max(1, min(J, CPU_BLOCK_CELLS // self.max_observed))

    @property
    def max_observed(self) -> int:
        """M: how many observed local cells one update evaluates (``observed_cells`` or L*L)."""
        return self.observed_cells or self.local_size ** 2

    @property
    def block(self) -> int:
        """Window alignment: bitmask blocks in "sample" mode, single cells otherwise."""
        return unknown.BLOCK if self.unknown_cells == "sample" else 1

    @property
    def reach(self) -> int:
        """Cells from a particle's cell to the farthest map cell its update can touch: every
        local cell centre lies within L / sqrt(2) cells of the particle (``observation_cells``)."""
        return math.ceil(self.local_size / math.sqrt(2.0)) + 1

    @property
    def window(self) -> int:
        """Side of a square global-map window that holds a rotated local map (the minimum map
        side; "sample" mode refreshes its known-cell bits over such a window)."""
        side = 2 * (self.reach + self.block)
        return int(unknown.BLOCK * math.ceil(side / unknown.BLOCK))

    def validate(self) -> "FilterConfig":
        H, W = self.map_shape
        if self.resampler not in resampling.RESAMPLERS:
            raise ValueError(f"resampler '{self.resampler}' unknown; choose one of "
                             f"{sorted(resampling.RESAMPLERS)}")
        if self.unknown_cells not in UNKNOWN_MODES:
            raise ValueError(f"unknown_cells '{self.unknown_cells}' unknown; choose one of "
                             f"{list(UNKNOWN_MODES)}")
        if H % unknown.BLOCK or W % unknown.BLOCK:
            raise ValueError(f"map_shape {self.map_shape} must be multiples of {unknown.BLOCK}")
        if min(H, W) < self.window:
            raise ValueError(f"map_shape {self.map_shape} is smaller than the update window "
                             f"{self.window} cells")
        if not 0 <= self.observed_cells <= self.local_size ** 2:
            raise ValueError(f"observed_cells {self.observed_cells} must lie in [0, "
                             f"{self.local_size ** 2}] (0: every local cell)")
        if self.unknown_samples < 1:
            raise ValueError("unknown_samples must be at least 1")
        if self.num_particles < 1:
            raise ValueError("num_particles must be at least 1")
        if self.particle_block < 0:
            raise ValueError(f"particle_block {self.particle_block} must be >= 0 (0: auto)")
        return self


class FilterParams(NamedTuple):
    """The continuous (tunable, differentiable) parameters."""

    motion: MotionParams = MotionParams()
    beta_prev: Array | float = 0.05
    beta_new: Array | float = 0.05


class FilterState(NamedTuple):
    """Particle set. known_bits is the unknown-cell sampler's state ([J, 0, 0, 2] if unused)."""

    pose: Array        # [J, 3]
    log_w: Array       # [J] normalised
    kmap: Array        # [J, H, W] degrees of freedom k
    smap: Array        # [J, H, W] sums of squared deviations S
    known_bits: Array  # [J, H/8, W/8, 2] uint32
    rows: Array        # [2] int32: map rows [lo, hi) that any update may have written so far
    best: Array        # [] int32: slot of the highest-weight particle at the last update, taken
                       # before its resampling (after one, the weights are all equal)


class UpdateNoise(NamedTuple):
    """Random numbers of one update: unknown-cell choices and resampling uniforms."""

    unknown_u: Array   # [J, unknown_samples] uniforms ([J, 0] in "ignore" mode)
    resample_u: Array  # [J]


class StepInfo(NamedTuple):
    """Per-frame outputs of ``step`` (stacked to [T, ...] by ``run_filter``)."""

    pose: Array          # [J, 3] after resampling
    ancestors: Array     # [J] index of each particle's parent before this frame's resampling
    best: Array          # [] slot of the highest-weight particle (FilterState.best)
    log_w: Array         # [J] normalised weights after the frame
    ess: Array           # ESS after the weight update, before resampling (eq. 23)
    resampled: Array     # bool
    updated: Array       # bool: the frame carried a local map
    log_lik: Array       # log mean weight increment (log marginal likelihood term), 0 if none
    extent_violations: Array  # particles with observed local cells outside the map extent
    empty_obs: Array     # bool: the local map had no informative cell
    dropped_cells: Array  # observed local cells beyond cfg.max_observed (0 when M suffices)


def init(cfg: FilterConfig, start_pose: Array | None = None) -> FilterState:
    """All particles at ``start_pose`` with equal weights and empty maps."""
    cfg.validate()
    J = cfg.num_particles
    H, W = cfg.map_shape
    start = jnp.zeros(3, jnp.float32) if start_pose is None else jnp.asarray(start_pose, jnp.float32)
    nb = (H // unknown.BLOCK, W // unknown.BLOCK) if cfg.unknown_cells == "sample" else (0, 0)
    return FilterState(
        pose=jnp.broadcast_to(start, (J, 3)),
        log_w=jnp.full((J,), -math.log(J), jnp.float32),
        kmap=jnp.zeros((J, H, W), jnp.float32),
        smap=jnp.zeros((J, H, W), jnp.float32),
        known_bits=jnp.zeros((J,) + nb + (2,), jnp.uint32),
        rows=jnp.array([H, 0], jnp.int32),
        best=jnp.int32(0),
    )


def motion_noise(key: Array, cfg: FilterConfig) -> Array:
    """Standard-normal motion draws [J, 2] for one frame (along-track, heading)."""
    return jax.random.normal(key, (cfg.num_particles, 2), jnp.float32)


def update_noise(key: Array, cfg: FilterConfig) -> UpdateNoise:
    """Uniforms for one update (unknown-cell sampling, then resampling)."""
    k_unknown, k_resample = jax.random.split(key)
    n = cfg.unknown_samples if cfg.unknown_cells == "sample" else 0
    return UpdateNoise(
        unknown_u=jax.random.uniform(k_unknown, (cfg.num_particles, n), jnp.float32),
        resample_u=resampling.draw_uniforms(k_resample, cfg.num_particles),
    )


def predict(pose: Array, u: Array, eps: Array, params: FilterParams) -> Array:
    """Prediction step (eq. 24) for all particles, given their standard-normal draws."""
    return apply_motion(pose, u, eps, params.motion)


def window_origin(pose: Array, cfg: FilterConfig) -> tuple[Array, Array, Array]:
    """Top-left cell (i, j) of the block-aligned window that holds a particle's footprint.

    Only "sample" mode uses it, to refresh the known-cell bits after a write. The ideal window
    is centred on the particle's cell (aligned to ``cfg.block``); a window that would leave the
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


class Observation(NamedTuple):
    """The observed cells of one local map, compacted (paper 6.3: compute where it matters).

    The first ``count`` entries are the cells with k > 0 in row-major order; the rest are
    padding (index 0, k = S = 0) up to the static length M = ``cfg.max_observed``.
    """

    index: Array    # [M] int32 flat local cell index a * L + b
    k: Array        # [M]
    S: Array        # [M]
    dropped: Array  # observed cells that did not fit in M (0 when M is large enough)


def compact_observation(local_obs: Array, cfg: FilterConfig) -> Observation:
    """[L, L, 2] local map (k, S) -> its observed cells (``Observation``), once per update."""
    M = cfg.max_observed
    k = local_obs[..., 0].reshape(-1)
    S = local_obs[..., 1].reshape(-1)
    observed = k > 0
    index = jnp.nonzero(observed, size=M, fill_value=0)[0].astype(jnp.int32)
    count = jnp.sum(observed)
    valid = jnp.arange(M) < count
    return Observation(index, jnp.where(valid, k[index], 0.0), jnp.where(valid, S[index], 0.0),
                       jnp.maximum(count - M, 0).astype(jnp.int32))


def observation_cells(pose: Array, local_index: Array, cfg: FilterConfig) -> tuple[Array, Array]:
    """The map cell under each given local cell seen from ``pose`` (paper 6.1: "rotate and
    translate the observation"): flat map indices and whether each lies inside the map.

    Local cell (a, b) (flat index a * L + b) covers robot-frame x in [a - L/2, a - L/2 + 1)
    cells (y likewise with b); its centre is rotated by the particle's heading, translated to
    its position, and takes the map cell it falls in. Every local cell lands in exactly one map
    cell, so no observation is dropped or counted twice; off-map cells get index H*W and are
    masked, never wrapped.
    """
    H, W = cfg.map_shape
    L = cfg.local_size
    # Robot position in cells, and local cell centres in cells (small numbers: float32-safe).
    px = (pose[0] - cfg.map_origin[0]) / cfg.resolution
    py = (pose[1] - cfg.map_origin[1]) / cfg.resolution
    ca = (local_index // L).astype(jnp.float32) - (L // 2) + 0.5
    cb = (local_index % L).astype(jnp.float32) - (L // 2) + 0.5
    c, s = jnp.cos(pose[2]), jnp.sin(pose[2])
    gi = jnp.floor(px + (c * ca - s * cb)).astype(jnp.int32)
    gj = jnp.floor(py + (s * ca + c * cb)).astype(jnp.int32)
    on_map = (gi >= 0) & (gi < H) & (gj >= 0) & (gj < W)
    return jnp.where(on_map, gi * W + gj, H * W), on_map


def log_importance(k_obs: Array, S_obs: Array, k_prior: Array, S_prior: Array,
                   k_borrow: Array, S_borrow: Array, can_borrow: Array,
                   params: FilterParams, unknown_cells: str) -> Array:
    """Tempered log importance factor of one particle, eqs. 26 and 30 / 31.

    All inputs are per-cell arrays of one footprint; (k_borrow, S_borrow) are the sampled known
    cells used for unknown cells in "sample" mode. Masked cells get harmless stand-ins so that
    neither the value nor the gradient sees a log(0).
    """
    return _log_importance(k_obs, S_obs, k_prior, S_prior, k_borrow, S_borrow, can_borrow,
                           params, unknown_cells)


def _log_importance(k_obs, S_obs, k_prior, S_prior, k_borrow, S_borrow, can_borrow,
                    params, unknown_cells, log_v=None):
    """``log_importance``; ``log_v`` (``cells.log_v_obs``) may be passed in when shared, and
    in "sample" mode k_borrow, S_borrow may be the draws themselves ([D], see below)."""
    log_pred = partial(cells.log_predictive_integer, log_v=log_v)
    has = k_obs > 0
    prev = has & (k_prior > 0)
    one = jnp.ones_like(k_obs)
    ko, So = jnp.where(has, k_obs, one), jnp.where(has, S_obs, one)
    lam_prev = log_pred(ko, So, jnp.where(prev, k_prior, one), jnp.where(prev, S_prior, one))
    sum_prev = jnp.sum(jnp.where(prev, lam_prev, 0.0))
    if unknown_cells == "ignore":  # eq. 30
        n_prev = jnp.sum(prev)
        return jnp.where(n_prev > 0, sum_prev / (params.beta_prev * jnp.maximum(n_prev, 1)), 0.0)
    if k_borrow.shape == k_obs.shape:
        new = has & ~prev & can_borrow & (k_borrow > 0)
        lam_new = log_pred(ko, So, jnp.where(new, k_borrow, one), jnp.where(new, S_borrow, one))
    else:
        # k_borrow, S_borrow are the draws [D]; cell c borrows draw c mod D. Eq. 26 runs over
        # the cells laid out [rows, D] with the draws broadcast over the rows: XLA CPU runs
        # that about 5x faster than over the draws tiled out to [M] (26 -> 5 ns per cell).
        M, D = k_obs.shape[0], k_borrow.shape[0]
        grid = partial(_by_draw, draws=D)
        log_v = cells.log_v_obs(k_obs, S_obs) if log_v is None else log_v
        kb = jnp.where(can_borrow & (k_borrow > 0), k_borrow, 0.0)[None, :]
        new_g = grid(has & ~prev) & (kb > 0)
        # padding: a cell with k = S = 1 (log v = 0), finite, never used (sliced off below)
        lam_g = cells.log_predictive_integer(grid(ko, fill=1), grid(So, fill=1),
                                             jnp.where(new_g, kb, 1.0),
                                             jnp.where(new_g, S_borrow[None, :], 1.0),
                                             log_v=grid(log_v))
        new = new_g.reshape(-1)[:M]
        lam_new = lam_g.reshape(-1)[:M]
    sum_new = jnp.sum(jnp.where(new, lam_new, 0.0))
    n_obs = jnp.maximum(jnp.sum(has), 1)
    return (sum_prev / params.beta_prev + sum_new / params.beta_new) / n_obs  # eq. 31


class _Footprint(NamedTuple):
    """What one update reads from the maps for a block of n particles ([n, ...] leaves)."""

    cells: Array     # [n, M] flat map index under each observed local cell (H*W off the map)
    off_map: Array   # [n] some observed local cell fell outside the map
    k_obs: Array     # [n, M] the observed cells, zero where their cell fell off the map
    S_obs: Array
    k_prior: Array   # [n, M] map statistics under the observed cells
    S_prior: Array
    k_draws: Array   # [n, unknown_samples] borrowed known cells ([n, 0] in "ignore" mode)
    S_draws: Array
    can_borrow: Array  # [n]


def _read_footprints(kflat: Array, sflat: Array, bits: Array, pose: Array, rows: Array,
                     unknown_u: Array, obs: Observation, cfg: FilterConfig) -> _Footprint:
    """Everything the update reads from the maps of particles ``rows`` ([n]; ``pose``, ``bits``
    and ``unknown_u`` are theirs). kflat, sflat: [J, H*W] maps of all particles."""
    flat, on_map = jax.vmap(lambda p: observation_cells(p, obs.index, cfg))(pose)
    k_obs = jnp.where(on_map, obs.k, 0.0)
    S_obs = jnp.where(on_map, obs.S, 0.0)
    if cfg.unknown_cells == "sample":
        # unknown_samples uniform known cells; observed cell c borrows draw c mod unknown_samples
        # (see _log_lambda), so every unknown cell borrows a uniformly random known cell (draws
        # are shared between cells unknown_samples apart, which keeps the search cost
        # independent of the local map). Only the draws are read from the big map.
        idx, total = jax.vmap(unknown.sample_known_cells)(bits, unknown_u)
        drawn = jnp.ones(idx.shape, bool)
        kb, Sb = _read_cells(kflat, rows, idx, drawn), _read_cells(sflat, rows, idx, drawn)
        can_borrow = total > 0
    else:
        kb = Sb = jnp.zeros((pose.shape[0], 0), kflat.dtype)
        can_borrow = jnp.zeros((pose.shape[0],), bool)
    return _Footprint(flat, jnp.any(~on_map & (obs.k > 0), axis=1), k_obs, S_obs,
                      _read_cells(kflat, rows, flat, on_map), _read_cells(sflat, rows, flat, on_map),
                      kb, Sb, can_borrow)


def _indices(maps: Array, rows: Array, cells_: Array) -> tuple[Array, ...]:
    """Index of cells_[i, m] of particle rows[i] in ``maps`` [J, H*W]: one flat index into
    ``maps.reshape(-1)`` where J*H*W fits int32 (a 1-D gather or scatter costs about a third
    less on CPU than a batched one), else the (row, cell) pair."""
    J, HW = maps.shape
    if J * HW < 2 ** 31:
        return (rows[:, None] * HW + cells_,)
    return jnp.broadcast_to(rows[:, None], cells_.shape), cells_


def _read_cells(maps: Array, rows: Array, cells_: Array, on_map: Array) -> Array:
    """maps[rows[i], cells_[i, m]] where on_map, else 0 ([J, H*W], [n], [n, M] -> [n, M])."""
    idx = _indices(maps, rows, jnp.where(on_map, cells_, 0))
    flat = maps.reshape(-1) if len(idx) == 1 else maps
    return jnp.where(on_map, flat.at[idx].get(mode="promise_in_bounds"), 0.0)


def _add_to_cells(maps: Array, rows: Array, cells_: Array, values: Array) -> Array:
    """maps[rows[i], cells_[i, m]] += values[m] (eq. 14); cells_ >= H*W (off the map) skipped.

    Skipped entries add 0 to cell 0 instead of being dropped as out of bounds, so the scatter
    can promise in-bounds indices: no bounds check per element (about 15% of the update on
    CPU, measured A/B in one process)."""
    on_map = cells_ < maps.shape[1]
    idx = _indices(maps, rows, jnp.where(on_map, cells_, 0))
    vals = jnp.where(on_map, jnp.broadcast_to(values, cells_.shape), 0.0)
    if len(idx) == 1:
        return maps.reshape(-1).at[idx].add(vals, mode="promise_in_bounds").reshape(maps.shape)
    return maps.at[idx].add(vals, mode="promise_in_bounds")


def _by_draw(x: Array, draws: int, fill: float = 0) -> Array:
    """[M] per-cell values -> [ceil(M / draws), draws], padded with ``fill``: cell c sits in
    column c mod draws, the column of the draw it borrows."""
    rows = -(-x.shape[0] // draws)
    return jnp.pad(x, (0, rows * draws - x.shape[0]), constant_values=fill).reshape(rows, draws)


def _log_lambda(f: _Footprint, log_v: Array, params: FilterParams, cfg: FilterConfig) -> Array:
    """[n] log importance factors from the stacked reads (eq. 26 with eq. 30 / 31); log_v [M]
    (``cells.log_v_obs`` of the observed cells) is shared by every particle. In "sample" mode
    observed cell c borrows draw c mod unknown_samples."""

    def one(k_obs, S_obs, k_prior, S_prior, kb, Sb, can_borrow):
        if cfg.unknown_cells != "sample":
            kb, Sb = k_obs, S_obs
        elif kb.shape[0] >= k_obs.shape[0]:
            kb, Sb = kb[:k_obs.shape[0]], Sb[:k_obs.shape[0]]
        return _log_importance(k_obs, S_obs, k_prior, S_prior, kb, Sb, can_borrow, params,
                               cfg.unknown_cells, log_v)

    return jax.vmap(one)(f.k_obs, f.S_obs, f.k_prior, f.S_prior, f.k_draws, f.S_draws,
                         f.can_borrow)


class _Weighed(NamedTuple):
    kflat: Array     # [J, H*W] maps after eq. 14
    sflat: Array
    log_lam: Array   # [J] log importance factors (eqs. 26, 30 / 31) against the old maps
    off_map: Array   # [J] some observed local cell fell outside the map


def _weigh_block(w: _Weighed, j0: Array, n: int, state: FilterState, obs: Observation,
                 log_v: Array, unknown_u: Array, params: FilterParams, cfg: FilterConfig
                 ) -> _Weighed:
    """Particles j0 .. j0+n-1: read their footprints, weigh them, add the local map."""
    rows = j0 + jnp.arange(n, dtype=jnp.int32)
    take = partial(lax.dynamic_slice_in_dim, start_index=j0, slice_size=n)
    f = _read_footprints(w.kflat, w.sflat, take(state.known_bits), take(state.pose), rows,
                         take(unknown_u), obs, cfg)
    log_lam = _log_lambda(f, log_v, params, cfg)
    kflat, sflat = w.kflat, w.sflat
    if cfg.update_map:
        # Write only after every read of these maps (the known-cell draws included): the
        # target cells are made to depend on the weights by a min() that never changes them
        # (cells <= H*W). Without that ordering XLA copies the whole maps before the update.
        after = (jnp.sum(log_lam) > 0).astype(jnp.int32)
        cells_ = jnp.minimum(f.cells, kflat.shape[1] + after)
        kflat = _add_to_cells(kflat, rows, cells_, obs.k)
        sflat = _add_to_cells(sflat, rows, cells_, obs.S)
    put = partial(lax.dynamic_update_slice_in_dim, start_index=j0, axis=0)
    return _Weighed(kflat, sflat, put(w.log_lam, log_lam), put(w.off_map, f.off_map))


def _weigh_and_write(state: FilterState, obs: Observation, unknown_u: Array,
                     params: FilterParams, cfg: FilterConfig) -> _Weighed:
    """Eq. 26 weights of every particle against its map, and eq. 14 into that map, one block
    of ``cfg.update_block`` particles at a time (see ``FilterConfig.particle_block``)."""
    J, H, W = state.kmap.shape
    B = cfg.update_block
    w = _Weighed(state.kmap.reshape(J, H * W), state.smap.reshape(J, H * W),
                 jnp.zeros((J,), state.log_w.dtype), jnp.zeros((J,), bool))
    # log v of each observed cell is shared by every particle: computed once, not J times.
    block = partial(_weigh_block, state=state, obs=obs, log_v=cells.log_v_obs(obs.k, obs.S),
                    unknown_u=unknown_u, params=params, cfg=cfg)
    full, tail = divmod(J, B)
    if full == 1:
        w = block(w, jnp.int32(0), B)
    else:
        w = lax.fori_loop(0, full, lambda b, w: block(w, b * B, B), w)
    if tail:
        w = block(w, jnp.int32(full * B), tail)
    return w


def written_rows(rows: Array, pose: Array, cfg: FilterConfig) -> Array:
    """``rows`` [lo, hi) widened to every map row an update from ``pose`` [J, 3] can write
    (``FilterConfig.reach`` rows either side of each particle's row)."""
    H, reach = cfg.map_shape[0], cfg.reach
    r = jnp.floor((pose[:, 0] - cfg.map_origin[0]) / cfg.resolution)
    r = jnp.clip(jnp.nan_to_num(r, nan=0.0), -reach, H + reach).astype(jnp.int32)
    return jnp.stack([jnp.maximum(jnp.minimum(rows[0], jnp.min(r) - reach), 0),
                      jnp.minimum(jnp.maximum(rows[1], jnp.max(r) + reach + 1), H)])


def _refresh_known_bits(kmap: Array, bits: Array, pose: Array, cfg: FilterConfig) -> Array:
    """"sample" mode: the known-cell bits around each particle's footprint, after eq. 14."""
    if cfg.unknown_cells != "sample" or not cfg.update_map:
        return bits

    def refresh(kmap, bits, pose):
        b, Wn = unknown.BLOCK, cfg.window
        oi, oj, _ = window_origin(pose, cfg)
        known = lax.dynamic_slice(kmap, (oi, oj), (Wn, Wn)) > 0
        return lax.dynamic_update_slice(bits, unknown.pack_known(known), (oi // b, oj // b, 0))

    return jax.vmap(refresh)(kmap, bits, pose)


def best_slot(log_w: Array, ancestors: Array) -> Array:
    """Slot of the highest-weight particle. ``log_w`` [J] are the normalised weights before the
    resampling that put particle ``ancestors[i]`` into slot i (the identity when none did).
    After a resampling the weights are all equal, so the choice is made on the weights before
    it; if the best particle left no offspring, this is the slot of the best one that did."""
    return jnp.argmax(log_w[ancestors]).astype(jnp.int32)


ROW_BAND = 64  # map rows per copy when resampling copies only the written rows


def gather_particles(particles, ancestors: Array, rows: Array | None = None):
    """``x[ancestors]`` for every array of the pytree ``particles`` ([J, ...] leaves), in place.

    ``ancestors`` must keep every surviving particle in its own slot (``resampling.
    keep_in_place``): then only the slots of particles without offspring are overwritten, one
    [H, W] map at a time, from slots that are never overwritten. No second [J, H, W] buffer is
    allocated, and only the dead particles' maps are copied (about a third of J for uniform
    weights) instead of all J. With ``rows`` [lo, hi) (``FilterState.rows``), the [J, H, W]
    leaves are copied only over those rows, in bands of ``ROW_BAND``: no update has written
    the others, which are zero in every map (e.g. 121 dead particles, 234 of 400 rows: 6.4-7.1
    ms against 9.4-10.7 ms for whole maps).
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


def update(state: FilterState, local_obs: Array, noise: UpdateNoise, params: FilterParams,
           cfg: FilterConfig) -> tuple[FilterState, StepInfo]:
    """Map update, importance weights (eq. 27), normalisation and ESS-gated resampling.

    local_obs: [L, L, 2] observation (k, S) of the local map, robot-centred.
    """
    J = cfg.num_particles
    obs = compact_observation(local_obs, cfg)
    w = _weigh_and_write(state, obs, noise.unknown_u, params, cfg)
    unnorm = state.log_w + w.log_lam
    log_lik = jax.nn.logsumexp(unnorm)  # log sum_j w_j lambda_j: the evidence increment
    log_w = unnorm - log_lik
    ess = resampling.ess(log_w)
    do_resample = ess < cfg.resample_ratio * J
    kmap, smap = w.kflat.reshape(state.kmap.shape), w.sflat.reshape(state.smap.shape)
    bits = _refresh_known_bits(kmap, state.known_bits, state.pose, cfg)
    rows = written_rows(state.rows, state.pose, cfg)

    def resample_branch(args):
        pose, kmap, smap, bits, log_w = args
        anc = resampling.keep_in_place(
            resampling.resample(cfg.resampler, jnp.exp(log_w), noise.resample_u))
        kmap, smap, bits = gather_particles((kmap, smap, bits), anc, rows)
        return jnp.take(pose, anc, axis=0), kmap, smap, bits, jnp.full((J,), -math.log(J), log_w.dtype), anc

    def keep_branch(args):
        pose, kmap, smap, bits, log_w = args
        return pose, kmap, smap, bits, log_w, jnp.arange(J, dtype=jnp.int32)

    pose, kmap, smap, bits, new_log_w, anc = lax.cond(
        do_resample, resample_branch, keep_branch, (state.pose, kmap, smap, bits, log_w))
    best = best_slot(log_w, anc)
    new_state = FilterState(pose, new_log_w, kmap, smap, bits, rows, best)
    info = StepInfo(pose=pose, ancestors=anc, best=best, log_w=new_log_w, ess=ess,
                    resampled=do_resample, updated=jnp.bool_(True), log_lik=log_lik,
                    extent_violations=jnp.sum(w.off_map).astype(jnp.int32),
                    empty_obs=~jnp.any(obs.k > 0), dropped_cells=obs.dropped)
    return new_state, info


def step(key: Array, state: FilterState, u: Array, local_obs: Array | None, params: FilterParams,
         cfg: FilterConfig) -> tuple[FilterState, StepInfo]:
    """One frame: predict, then update if ``local_obs`` is given (Python-level choice)."""
    k_motion, k_update = jax.random.split(key)
    pose = predict(state.pose, u, motion_noise(k_motion, cfg), params)
    state = state._replace(pose=pose)
    if local_obs is None:
        return state, _no_update_info(state, cfg)
    return update(state, local_obs, update_noise(k_update, cfg), params, cfg)


def _no_update_info(state: FilterState, cfg: FilterConfig) -> StepInfo:
    J = cfg.num_particles
    return StepInfo(pose=state.pose, ancestors=jnp.arange(J, dtype=jnp.int32), best=state.best,
                    log_w=state.log_w,
                    ess=resampling.ess(state.log_w), resampled=jnp.bool_(False),
                    updated=jnp.bool_(False), log_lik=jnp.float32(0.0),
                    extent_violations=jnp.int32(0), empty_obs=jnp.bool_(False),
                    dropped_cells=jnp.int32(0))


class RunOutput(NamedTuple):
    """What ``run_filter`` returns."""

    final_state: FilterState
    infos: StepInfo         # stacked per frame: pose [T, J, 3], ancestors [T, J], ess [T], ...
    best_pose: Array        # [T, 3] highest-weight particle at each frame
    mean_pose: Array        # [T, 3] weighted mean (circular mean for theta)
    best_path: Array        # [T, 3] path of the final best particle, through its ancestry


def _summaries(info: StepInfo) -> tuple[Array, Array]:
    w = jnp.exp(info.log_w)
    best = info.pose[info.best]
    xy = w @ info.pose[:, :2]
    th = jnp.arctan2(w @ jnp.sin(info.pose[:, 2]), w @ jnp.cos(info.pose[:, 2]))
    return best, jnp.concatenate([xy, th[None]])


def backtrack_path(poses: Array, ancestors: Array, last: Array) -> Array:
    """Follow ancestry back from particle ``last`` at the final frame: [T, J, 3] -> [T, 3]."""

    def back(j, xs):
        pose_t, anc_t = xs
        return anc_t[j], pose_t[j]

    _, path = lax.scan(back, last, (poses, ancestors), reverse=True)
    return path


@partial(jax.jit, static_argnames=("cfg",), donate_argnums=(0,))
def scan_frames(state: FilterState, keys: Array, controls: Array, obs_index: Array,
                local_obs: Array, params: FilterParams, cfg: FilterConfig
                ) -> tuple[FilterState, tuple[StepInfo, Array, Array]]:
    """``lax.scan`` of predict (every frame) and update (frames with obs_index >= 0).

    keys [T], controls [T, 3], obs_index [T] (index into local_obs or -1), local_obs
    [M, L, L, 2] observations (k, S) from ``cells.obs_from_stats`` with M >= 1.
    Returns the final state and per-frame (StepInfo, best pose, weighted-mean pose).
    ``state`` is donated: the maps are updated in its buffers, so do not use it afterwards
    (pass ``jax.tree.map(jnp.copy, state)`` to keep it).
    """

    def frame(state, xs):
        k, u, idx = xs
        k_motion, k_update = jax.random.split(k)
        pose = predict(state.pose, u, motion_noise(k_motion, cfg), params)
        state = state._replace(pose=pose)
        obs = local_obs[jnp.maximum(idx, 0)]
        state, info = lax.cond(
            idx >= 0,
            lambda s: update(s, obs, update_noise(k_update, cfg), params, cfg),
            lambda s: (s, _no_update_info(s, cfg)),
            state)
        best, mean = _summaries(info)
        return state, (info, best, mean)

    return lax.scan(frame, state, (keys, controls, obs_index))


def frame_keys(key: Array, num_frames: int) -> Array:
    """Per-frame keys: frame t always uses the same key, however the run is chunked."""
    return jax.random.split(key, num_frames)


@partial(jax.jit, static_argnames=("cfg",))
def run_filter(key: Array, params: FilterParams, controls: Array, obs_index: Array,
               local_obs: Array, cfg: FilterConfig, start_pose: Array | None = None) -> RunOutput:
    """The whole filter in one jitted call (see ``scan_frames``); vmappable and differentiable
    in ``params``."""
    state = init(cfg, start_pose)
    final, (infos, best, mean) = scan_frames(
        state, frame_keys(key, controls.shape[0]), controls, obs_index, local_obs, params, cfg)
    path = backtrack_path(infos.pose, infos.ancestors, final.best)
    return RunOutput(final, infos, best, mean, path)
