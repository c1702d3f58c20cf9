"""The dense JAX filter run and timed for ``gslam compare``: the whole run after compilation,
one update alone on its final maps (as ``gslam bench``), and every update as the run executes
it, resampling included (as the tiled reference times its own)."""

from __future__ import annotations

import time
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gslam_jax import rbpf
from gslam_jax.rbpf import maps
from gslam_jax.run import Run

__all__ = ["DenseOutput", "run_dense", "time_dense_updates"]


class DenseOutput(NamedTuple):
    pose: np.ndarray          # [T, J, 3]
    log_w: np.ndarray         # [T, J]
    ess: np.ndarray           # [T]
    resampled: np.ndarray     # [T]
    kmap: np.ndarray          # [J, H, W]
    smap: np.ndarray
    state_bytes: int          # bytes of the dense particle state (maps, bitmasks, poses, weights):
    #                           fixed shapes, so the same at every frame (XLA's temporaries aside)
    seconds: float            # whole run after compilation
    update_seconds: float     # one local-map update (median of repeats, jitted, donated state)
    run_update_seconds: np.ndarray = np.zeros(0)  # [M] each update as the run executes it
    run_resampled: np.ndarray = np.zeros(0, bool)  # [M] whether each of those updates resampled
    live_bytes: int = 0       # shared store: most bytes its live tiles held at once (with the
    #                           page tables); dense: state_bytes
    ancestors: np.ndarray | None = None  # [T, J] each slot's parent at each frame


def _state_bytes(state: rbpf.FilterState) -> int:
    return int(sum(np.asarray(x).nbytes for x in jax.tree.leaves(state)))


def _live_bytes(state: rbpf.FilterState, cfg: rbpf.FilterConfig) -> int:
    """Shared store: the peak of its live tiles' bytes plus its page tables and bookkeeping
    (what the tiled reference's ledger counts, and the indices); dense: the whole state."""
    return _state_bytes(state) - maps.map_bytes(cfg) + maps.peak_bytes(state.maps, cfg)


def time_dense_updates(key: jax.Array, params: rbpf.FilterParams, run: Run, obs: np.ndarray,
                       cfg: rbpf.FilterConfig, fallback: np.ndarray | None = None
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Wall time of every local-map update as the run executes it, resampling included (as the
    tiled reference's times are): the run replayed frame by frame through ``rbpf.step`` (the
    frame of ``run_filter``, same draws), jitted with the state donated. A timed call is the
    frame's predict (negligible beside the update) and its update.

    The per-frame inputs are sliced into lists of device arrays beforehand, so that no eager
    JAX indexing lands in a timed call.

    ``fallback`` [T] bool: the frames of the fallback odometry (``run_dense``).

    Returns [M] seconds and [M] whether each update resampled."""
    all_keys = rbpf.frame_keys(key, run.num_frames)
    step = jax.jit(lambda k, s, u, local, h=0.0, f=False: rbpf.step(
        k, s, u, local, params, cfg, lattice_heading=h, fallback=f), donate_argnums=1)
    flags = [jnp.bool_(f) for f in (np.zeros(run.num_frames, bool) if fallback is None
                                    else np.asarray(fallback))]
    headings = [jnp.float32(h) for h in run.lattice_heading_array()]
    keys = [all_keys[t] for t in range(run.num_frames)]
    controls = [jnp.asarray(u) for u in np.asarray(run.controls, np.float32)]
    local_obs = [jnp.asarray(o) for o in np.asarray(obs)]
    start = jnp.asarray(run.start_pose(), jnp.float32)
    jax.block_until_ready(keys + controls + local_obs + flags)
    # compile, with the timed calls' argument types
    jax.block_until_ready(step(keys[0], rbpf.init(cfg, start), controls[0], local_obs[0],
                               headings[0], flags[0]))
    state = rbpf.init(cfg, start)
    times, resampled = [], []
    for t, idx in enumerate(np.asarray(run.obs_index)):
        flag = flags[t]
        if idx < 0:
            state, _ = step(keys[t], state, controls[t], None, 0.0, flag)
            continue
        jax.block_until_ready(state)
        t0 = time.perf_counter()
        state, info = jax.block_until_ready(step(keys[t], state, controls[t], local_obs[idx],
                                                 headings[idx], flag))
        times.append(time.perf_counter() - t0)
        resampled.append(bool(info.resampled))
    return np.array(times), np.array(resampled, bool)


def run_dense(key: jax.Array, params: rbpf.FilterParams, run: Run, obs: np.ndarray,
              cfg: rbpf.FilterConfig, repeats: int = 5,
              fallback: np.ndarray | None = None) -> DenseOutput:
    """The dense filter over the Run (compiled once, then timed), the update alone on its final
    maps, and every update as the run executes it (``time_dense_updates``); where
    ``fallback[t]`` (None: nowhere), frame t's motion noise is ``params.motion.fallback_scale``
    times the VO's. The state's bytes
    are those of its fixed-shape arrays, allocated once: the same at every frame."""
    args = (key, params, jnp.asarray(run.controls, jnp.float32),
            jnp.asarray(run.obs_index, jnp.int32), jnp.asarray(obs), cfg,
            jnp.asarray(run.start_pose(), jnp.float32), jnp.asarray(run.lattice_heading_array()),
            None if fallback is None else jnp.asarray(fallback, bool))
    jax.block_until_ready(rbpf.run_filter(*args))  # compile
    t0 = time.perf_counter()
    out = jax.block_until_ready(rbpf.run_filter(*args))
    seconds = time.perf_counter() - t0
    i = jax.device_get(out.infos)
    maps.check_status(int(np.max(i.map_status)), cfg)
    kmap, smap, _ = (np.asarray(x) for x in maps.to_dense(out.final_state.maps, cfg))
    nbytes, live = _state_bytes(out.final_state), _live_bytes(out.final_state, cfg)
    # One update on the final maps, state donated as in the scan; ``update`` does not
    # resample, so every repeat does the same work (as gslam bench).
    upd = jax.jit(partial(rbpf.update, cfg=cfg), donate_argnums=0)
    state = jax.tree.map(jnp.copy, out.final_state)
    del out
    noise = rbpf.update_noise(jax.random.key(1), cfg)
    last = int(np.max(run.obs_index))
    local = jnp.asarray(obs[last])
    heading = jnp.float32(run.lattice_heading_array()[last])
    state, _ = jax.block_until_ready(upd(state, local, noise.unknown_u, params,
                                         lattice_heading=heading))
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        state, _ = jax.block_until_ready(upd(state, local, noise.unknown_u, params,
                                             lattice_heading=heading))
        times.append(time.perf_counter() - t)
    del state
    run_times, resampled = time_dense_updates(key, params, run, obs, cfg, fallback)
    return DenseOutput(i.pose, i.log_w, i.ess, i.resampled, kmap, smap, nbytes, seconds,
                       float(np.median(times)), run_times, resampled, live, i.ancestors)
