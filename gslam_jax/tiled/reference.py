"""The Gamma-SLAM particle filter on copy-on-write tiled maps, in NumPy (paper 6.1-6.3).

Same filter as the dense JAX one, written independently: every frame predicts with the motion
model (eqs. 1-3); a frame with a local map updates each particle's map window and weight
(eqs. 14, 26, 27, 30/31), normalises, and resamples when the ESS (eq. 23) < ratio * J.

Shared semantics with the dense filter (they define "the same numbers"):

* Each robot-centred local cell's centre, rotated by the particle's heading and translated to
  its position (float32: cells = (metres - origin) * float32(1 / resolution)), falls in one
  map cell; that cell is its prior and receives its statistics. Cells that fall off the map
  are skipped (the particle is flagged).
* "sample" mode: each particle gets ``unknown_samples`` uniforms u; draw d is its
  floor(u_d * N_known)-th known cell in the order (8 x 8 blocks row-major, row-major inside a
  block); the c-th observed local cell (k > 0, counted row-major from 0) borrows draw
  c mod unknown_samples, for the weight only.
* Random numbers come from the dense module's drawing functions, so both filters see the same
  draws; nothing else of the dense implementation is used. ``draw_noise`` makes every frame's
  draws up front, as NumPy arrays, so that no JAX compilation, dispatch or copy lands in the
  run's loop (or in its timings).
* Where the two differ only by rounding (float32 weights against these float64 ones), the
  reference can follow the other filter: given its per-frame resampling decisions and ancestors
  as data (``Decisions``), a decision whose ESS lies within rounding of the threshold, or
  ancestors that need only draws within rounding of a cumulative-weight boundary moved
  (``numerics.follow_ancestors``), are taken from it and reported as a ``RoundingEvent``; any
  larger difference is kept, so the runs part and the comparison says where.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, NamedTuple

import jax
import numpy as np

from gslam_jax.rbpf import FilterConfig, FilterParams, UpdateNoise, frame_keys, motion_noise, update_noise
from gslam_jax.tiled import numerics as nm
from gslam_jax.tiled.tiles import Ledger, TileMap, tile_cells

__all__ = ["DEFAULT_TILE_SIZE", "TiledState", "UpdateInfo", "TiledOutput", "Draws",
           "Decisions", "RoundingEvent",
           "cells_per_metre", "footprint", "init", "predict", "update", "draw_noise", "run_tiled",
           "memory_snapshot"]

DEFAULT_TILE_SIZE = 10.0  # metres (paper 6.3)
F32 = np.float32
BLOCK = 8


def cells_per_metre(cfg: FilterConfig) -> np.float32:
    """float32(1 / resolution): metres become cells by this multiplication (as XLA compiles a
    division by the constant resolution), so both filters place a pose in the same cell."""
    return F32(1) / F32(cfg.resolution)


def footprint(pose: np.ndarray, cfg: FilterConfig,
              cos_sin: tuple[np.float32, np.float32]) -> tuple[np.ndarray, np.ndarray]:
    """Map cell (i, j) [L*L, 2] under each local cell's centre (row-major over the local map),
    and whether it lies inside the map. float32 arithmetic, as the dense filter does it."""
    H, W = cfg.map_shape
    L, inv = cfg.local_size, cells_per_metre(cfg)
    px = (pose[0] - F32(cfg.map_origin[0])) * inv  # robot position in cells
    py = (pose[1] - F32(cfg.map_origin[1])) * inv
    centre = np.arange(L, dtype=F32) - F32(L // 2) + F32(0.5)
    c, s = cos_sin
    a, b = centre[:, None], centre[None, :]
    gi = np.floor(px + (c * a - s * b)).astype(np.int64).ravel()
    gj = np.floor(py + (s * a + c * b)).astype(np.int64).ravel()
    inside = (gi >= 0) & (gi < H) & (gj >= 0) & (gj < W)
    return np.stack([gi, gj], axis=1), inside


@dataclass
class TiledState:
    """Particles: float32 poses [J, 3], float64 normalised log weights [J] (more accurate than
    the dense float32 ones, which agree to ~1e-5 per update), tiled maps."""

    pose: np.ndarray
    log_w: np.ndarray
    maps: list[TileMap]
    ledger: Ledger = field(default_factory=Ledger)


class Decisions(NamedTuple):
    """Another filter's resampling, per frame, for the reference to follow where its own
    differs only by rounding: ``resampled`` [T] bool and ``ancestors`` [T, J] (slot i's parent,
    arranged as ``numerics.survivors_keep_slots`` arranges them)."""

    resampled: np.ndarray
    ancestors: np.ndarray


class RoundingEvent(NamedTuple):
    """A frame where the reference took the other filter's choice: ``kind`` "decision" (the
    ESS ``value`` within ``numerics.ESS_ROUNDING`` of the threshold) or "ancestors" (``moved``
    draws, each at most ``value`` from a cumulative-weight boundary)."""

    frame: int
    kind: str
    value: float
    moved: int = 0


class UpdateInfo(NamedTuple):
    log_lam: np.ndarray      # [J] tempered log importance factors
    ess: float               # before resampling
    resampled: bool
    ancestors: np.ndarray    # [J]
    extent_violations: int
    rounding: tuple = ()     # RoundingEvents (frame -1: the caller knows the frame)


def init(cfg: FilterConfig, tile_size: float = DEFAULT_TILE_SIZE,
         start_pose: np.ndarray | None = None) -> TiledState:
    """All particles at ``start_pose`` with equal weights and empty (tile-less) maps."""
    cfg.validate()
    side = tile_cells(tile_size, cfg.resolution)
    J = cfg.num_particles
    start = np.zeros(3, F32) if start_pose is None else np.asarray(start_pose, F32)
    ledger = Ledger()
    return TiledState(pose=np.tile(start, (J, 1)), log_w=np.full(J, -math.log(J)),
                      maps=[TileMap(side, ledger) for _ in range(J)], ledger=ledger)


def predict(state: TiledState, u: np.ndarray, eps: np.ndarray, params: FilterParams,
            noise_scale: float = 1.0) -> None:
    """Motion model (eqs. 1-3, 24) for every particle, in place; every noise std times
    ``noise_scale`` (a frame of the fallback odometry, ``[motion] fallback_scale``)."""
    m = params.motion
    s = float(noise_scale)
    state.pose = nm.apply_motion(state.pose, u, eps, float(m.alpha_d) * s,
                                 float(m.alpha_theta_d) * s, float(m.alpha_theta) * s,
                                 float(m.alpha_cross) * s)


def _particle(tmap: TileMap, pose: np.ndarray, cs: tuple, obs: np.ndarray, u: np.ndarray,
              params: FilterParams, cfg: FilterConfig) -> tuple[float, bool]:
    """Map update and tempered log importance factor of one particle (eqs. 14, 26, 30/31)."""
    ij, inside = footprint(pose, cfg, cs)
    k_loc = obs[..., 0].ravel()
    S_loc = obs[..., 1].ravel()
    off_map = bool(np.any(~inside & (k_loc > 0)))
    k_obs = np.where(inside, k_loc, F32(0))
    S_obs = np.where(inside, S_loc, F32(0))
    # The footprint's bounding box, read from the tiles as one window.
    if inside.any():
        lo, hi = ij[inside].min(axis=0), ij[inside].max(axis=0) + 1
    else:
        lo, hi = np.zeros(2, np.int64), np.ones(2, np.int64)
    rel = np.where(inside[:, None], ij - lo, 0)
    k_box, S_box = tmap.read(int(lo[0]), int(lo[1]), int(hi[0] - lo[0]), int(hi[1] - lo[1]))
    k_prior = np.where(inside, k_box[rel[:, 0], rel[:, 1]], F32(0))
    S_prior = np.where(inside, S_box[rel[:, 0], rel[:, 1]], F32(0))
    has = k_obs > 0
    prev = has & (k_prior > 0)
    sum_prev = float(np.sum(nm.log_predictive(k_obs[prev], S_obs[prev], k_prior[prev],
                                              S_prior[prev])))
    sum_new = 0.0
    if cfg.unknown_cells == "sample":
        new = has & ~prev
        keys, kk, SS = tmap.known_cells(cfg.map_shape[1] // BLOCK)  # cached per tile
        if keys.size and new.any():
            total = keys.size
            r = np.clip(np.floor(u * F32(total)).astype(np.int64), 0, total - 1)
            rank = np.cumsum(k_loc > 0) - 1  # c-th observed local cell borrows draw c mod N
            c = rank[new] % cfg.unknown_samples
            pick = r[c]
            sum_new = float(np.sum(nm.log_predictive(k_obs[new], S_obs[new], kk[pick], SS[pick])))
    log_lam = nm.combine(sum_prev, int(prev.sum()), sum_new, int(has.sum()),
                         float(params.beta_prev), float(params.beta_new), cfg.unknown_cells)
    if cfg.update_map:  # eq. 14, pooled where two local cells share a map cell
        dk = np.zeros_like(k_box)
        dS = np.zeros_like(S_box)
        np.add.at(dk, (rel[has, 0], rel[has, 1]), k_obs[has])
        np.add.at(dS, (rel[has, 0], rel[has, 1]), S_obs[has])
        tmap.add(int(lo[0]), int(lo[1]), dk, dS)
    return log_lam, off_map


def update(state: TiledState, obs: np.ndarray, noise: UpdateNoise, params: FilterParams,
           cfg: FilterConfig, follow: tuple[bool, np.ndarray] | None = None,
           lattice_heading: float = 0.0) -> UpdateInfo:
    """One local map: per-particle update, weights (eq. 27), normalisation, ESS-gated
    resampling; state is updated in place. obs: [L, L, 2] float32 (k, S) on a lattice turned
    by ``lattice_heading`` radians against the robot (its cells are placed at the particle's
    heading plus that angle). ``follow``: another filter's (resampled, ancestors) at this
    frame, taken where this one's differ only by rounding (reported in
    ``UpdateInfo.rounding``)."""
    J = cfg.num_particles
    obs = np.asarray(obs, F32)
    unknown_u = np.asarray(noise.unknown_u, F32)
    heading = (state.pose[:, 2] + F32(lattice_heading)).astype(F32)
    c, s = nm.cos32(heading), nm.sin32(heading)
    log_lam = np.zeros(J)
    violations = 0
    for j in range(J):
        log_lam[j], off_map = _particle(state.maps[j], state.pose[j], (c[j], s[j]), obs,
                                        unknown_u[j] if unknown_u.size else unknown_u, params, cfg)
        violations += int(off_map)
    phi = (nm.tempering_exponent(state.log_w, log_lam, cfg.ess_target)
           if cfg.tempering == "adaptive" else 1.0)
    unnorm = state.log_w + phi * log_lam
    top = unnorm.max()
    log_w = unnorm - (top + math.log(np.sum(np.exp(unnorm - top))))
    e = nm.ess(log_w)
    anc = np.arange(J)
    # at the threshold (within 0.1%, where adaptive tempering lands) counts as below it
    threshold = nm.resample_threshold(cfg.resample_ratio, J)
    resampled = bool(e < threshold)
    rounding = []
    if follow is not None and bool(follow[0]) != resampled and \
            nm.decision_within_rounding(e, threshold):
        resampled = bool(follow[0])
        rounding.append(RoundingEvent(-1, "decision", e))
    if resampled:
        w, u = np.exp(log_w), np.asarray(noise.resample_u)
        anc = nm.survivors_keep_slots(nm.resample(cfg.resampler, w, u))
        if follow is not None and bool(follow[0]) and not np.array_equal(anc, follow[1]):
            taken = nm.follow_ancestors(cfg.resampler, w, u, follow[1])
            if taken is not None:
                anc = taken[0]
                rounding.append(RoundingEvent(-1, "ancestors", taken[2], taken[1]))
        old = state.maps
        state.maps = [old[a].share() for a in anc]
        for m in old:
            m.release()
        state.pose = state.pose[anc]
        log_w = np.full(J, -math.log(J))
    state.log_w = log_w
    return UpdateInfo(log_lam, e, bool(resampled), anc, violations, tuple(rounding))


def memory_snapshot(state: TiledState) -> dict:
    """Bytes held by live tiles (cells and known-cell caches; ``cache_bytes`` the caches alone),
    distinct tiles, and tiles shared per particle (mean, max)."""
    shared = [sum(t.refs > 1 for t in m.tiles.values()) for m in state.maps]
    held = [len(m.tiles) for m in state.maps]
    return {"bytes": state.ledger.live_bytes, "cache_bytes": state.ledger.cache_bytes,
            "tiles": state.ledger.live_tiles,
            "shared_mean": float(np.mean(shared)), "shared_max": int(max(shared)),
            "held_mean": float(np.mean(held))}


class TiledOutput(NamedTuple):
    """Per-frame outputs of ``run_tiled`` ([T, ...]) and the final state."""

    pose: np.ndarray           # [T, J, 3] after resampling
    log_w: np.ndarray          # [T, J]
    ess: np.ndarray            # [T] (after the weight update, before resampling)
    resampled: np.ndarray      # [T] bool
    ancestors: np.ndarray      # [T, J]
    memory_bytes: np.ndarray   # [T] bytes held by tiles after the frame (cells + known caches)
    tiles: np.ndarray          # [T] distinct live tiles
    shared_mean: np.ndarray    # [T] tiles shared per particle (mean)
    update_seconds: np.ndarray  # [M] wall time of each local-map update (``update`` alone)
    peak_bytes: int            # most bytes held by tiles at any time (cells + known caches)
    extent_violations: int
    final: TiledState
    rounding: tuple = ()       # RoundingEvents: where the reference followed ``Decisions``


def _draw_fns(cfg: FilterConfig) -> tuple[Callable, Callable]:
    """Jitted per-frame draws, split exactly as the dense scan splits each frame key."""

    def motion(k):
        return motion_noise(jax.random.split(k)[0], cfg)

    def upd(k):
        return update_noise(jax.random.split(k)[1], cfg)

    return jax.jit(motion), jax.jit(upd)


class Draws(NamedTuple):
    """Every frame's random numbers as NumPy arrays (``draw_noise``)."""

    motion: list[np.ndarray]       # [T] standard normals [J, 2]
    update: dict[int, UpdateNoise]  # frame -> uniforms, for the frames with a local map


def draw_noise(key: jax.Array, obs_index: np.ndarray, cfg: FilterConfig) -> Draws:
    """The dense filter's per-frame random numbers (``frame_keys``; each frame key split into
    motion and update keys), drawn frame by frame by jitted functions (compiled on the first
    call) and copied to NumPy: what ``run_tiled`` consumes, made before it runs."""
    obs_index = np.asarray(obs_index)
    keys = frame_keys(key, len(obs_index))
    draw_motion, draw_update = _draw_fns(cfg)
    motion, update_ = [], {}
    for t in range(len(obs_index)):
        k = keys[t]
        motion.append(np.asarray(draw_motion(k)))
        if obs_index[t] >= 0:
            update_[t] = jax.tree.map(np.asarray, draw_update(k))
    return Draws(motion, update_)


def _host_params(params: FilterParams) -> FilterParams:
    """``params`` as Python floats (one device-to-host copy), so the run reads no JAX array."""
    return jax.tree.map(float, jax.device_get(params))


def run_tiled(key: jax.Array, params: FilterParams, controls: np.ndarray, obs_index: np.ndarray,
              local_obs: np.ndarray, cfg: FilterConfig, tile_size: float = DEFAULT_TILE_SIZE,
              start_pose: np.ndarray | None = None,
              progress: Callable[[int, int], None] | None = None,
              draws: Draws | None = None, follow: Decisions | None = None,
              lattice_headings: np.ndarray | None = None,
              noise_scale: np.ndarray | None = None) -> TiledOutput:
    """The whole run, frame by frame, with the dense filter's per-frame random numbers
    (local map m on a lattice turned by ``lattice_headings[m]``, ``Run.lattice_headings``;
    None: all 0; frame t's motion noise times ``noise_scale[t]``, None: all 1):
    ``draws`` (``draw_noise(key, obs_index, cfg)``, made here first when not given; pass them
    to time the run alone). With ``draws`` given, the loop is NumPy only: ``key`` is unused.
    ``follow``: another filter's resampling decisions, taken where they differ from the
    reference's only by rounding (``TiledOutput.rounding`` lists those frames)."""
    state = init(cfg, tile_size, start_pose)
    obs_index = np.asarray(obs_index)
    if draws is None:
        draws = draw_noise(key, obs_index, cfg)
    params = _host_params(params)
    controls = np.asarray(controls, F32)
    local_obs = np.asarray(local_obs, F32)
    T, J = controls.shape[0], cfg.num_particles
    if len(draws.motion) != T:
        raise ValueError(f"draws for {len(draws.motion)} frames, the run has {T}")
    if follow is not None and (np.shape(follow.resampled) != (T,) or
                               np.shape(follow.ancestors) != (T, J)):
        raise ValueError(f"decisions to follow of shapes {np.shape(follow.resampled)} and "
                         f"{np.shape(follow.ancestors)}, the run needs [{T}] and [{T}, {J}]")
    out = {n: [] for n in ("pose", "log_w", "ess", "resampled", "ancestors", "mem", "tiles", "shared")}
    upd_s, violations, rounding = [], 0, []
    snap = memory_snapshot(state)
    for t in range(T):
        predict(state, controls[t], draws.motion[t], params,
                1.0 if noise_scale is None else noise_scale[t])
        ess, resampled, anc = nm.ess(state.log_w), False, np.arange(J)
        if obs_index[t] >= 0:
            noise = draws.update[t]
            t0 = time.perf_counter()
            m = int(obs_index[t])
            info = update(state, local_obs[m], noise, params, cfg,
                          None if follow is None else (follow.resampled[t], follow.ancestors[t]),
                          0.0 if lattice_headings is None else float(lattice_headings[m]))
            upd_s.append(time.perf_counter() - t0)
            ess, resampled, anc = info.ess, info.resampled, info.ancestors
            rounding.extend(r._replace(frame=t) for r in info.rounding)
            violations += info.extent_violations
            snap = memory_snapshot(state)
        for name, v in (("pose", state.pose.copy()), ("log_w", state.log_w.copy()), ("ess", ess),
                        ("resampled", resampled), ("ancestors", anc), ("mem", snap["bytes"]),
                        ("tiles", snap["tiles"]), ("shared", snap["shared_mean"])):
            out[name].append(v)
        if progress is not None:
            progress(t + 1, T)
    return TiledOutput(
        pose=np.stack(out["pose"]), log_w=np.stack(out["log_w"]), ess=np.array(out["ess"]),
        resampled=np.array(out["resampled"]), ancestors=np.stack(out["ancestors"]),
        memory_bytes=np.array(out["mem"], np.int64), tiles=np.array(out["tiles"]),
        shared_mean=np.array(out["shared"]), update_seconds=np.array(upd_s),
        peak_bytes=state.ledger.peak_bytes, extent_violations=violations, final=state,
        rounding=tuple(rounding))
