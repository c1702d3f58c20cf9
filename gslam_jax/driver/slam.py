"""Running Gamma-SLAM on a Run: the chunked scan of the filter over its frames (the pool
regrown where a chunk ran out of tiles), the checks of what each chunk returns
(``chunk_checks``), and the results (``results``).

This is the host-side driver the CLI, the experiments and the benchmarks share. The filter math
lives in ``rbpf``; the settings for a Run in ``sizing``, its observations in ``observations``,
map reuse in ``map_reuse``, the axes of the map's lattice in ``map_axes``; the device arrays the
search and the tuner feed the filter in ``device_arrays``.
"""

from __future__ import annotations

import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from gslam_jax import rbpf
from gslam_jax.config import Config
from gslam_jax.driver.chunk_checks import (check_map_status, check_observed_cells, check_weights,
                                           pool_ran_out)
from gslam_jax.driver.machine import release_free_heap
from gslam_jax.driver.map_axes import check_local_lattices, filtered_run
from gslam_jax.driver.map_reuse import PriorMap, prior_state
from gslam_jax.driver.observations import map_observations
from gslam_jax.driver.results import Ancestry, ChunkReport, PathEstimates, SlamResult
from gslam_jax.driver.sizing import fallback_frames, filter_config, filter_params, map_memory
from gslam_jax.errors import ArgumentError, integer_argument
from gslam_jax.gridmap import turn_poses
from gslam_jax.rbpf import maps
from gslam_jax.run import Run

__all__ = ["run_slam", "run_filter_config"]


def run_filter_config(run: Run, config: Config, prior: PriorMap | None = None
                      ) -> rbpf.FilterConfig:
    """The static filter config ``run_slam`` runs ``run`` with (sized on the map lattice's
    axes, ``filtered_run``), e.g. for ``online.Online(filter_config=...)`` to reproduce it."""
    return filter_config(config, filtered_run(run, config, prior)[2], prior)


def _scan_chunk(state: rbpf.FilterState, start: int, frames: tuple, obs: jax.Array,
                headings: jax.Array, params: rbpf.FilterParams, cfg: rbpf.FilterConfig,
                growth: maps.PoolGrowth | None) -> tuple[rbpf.FilterState, tuple,
                                                          rbpf.FilterConfig]:
    """``rbpf.scan_frames`` over one chunk of ``frames`` (keys, controls, obs_index,
    fallback flags or None) from frame ``start`` (local maps ``obs`` on lattices turned by
    ``headings``), its outputs on the host. With an automatic pool (``growth``) the chunk is run
    again from its start, in a grown pool, when it ran out of tiles (as long as the memory
    allows; otherwise its outputs carry the status that ``check_map_status`` names)."""
    keys, controls, obs_index, fallback = frames

    def scan(s: rbpf.FilterState, cfg: rbpf.FilterConfig) -> tuple[rbpf.FilterState, tuple]:
        return rbpf.scan_frames(s, keys, controls, obs_index, obs, params, cfg, headings,
                                fallback)

    if growth is None:
        state, out = scan(state, cfg)
        return state, jax.device_get(out), cfg
    growth.before(state.maps)
    kept = jax.tree.map(jnp.copy, state)  # scan_frames donates the state it is given
    while True:
        state, out = scan(state, cfg)
        out = jax.device_get(out)
        ran_out = pool_ran_out(out[0])
        regrown = ran_out and growth.regrow(kept.maps, cfg, start, start + ran_out - 1)
        if not regrown:
            return state, out, cfg
        kept, cfg = kept._replace(maps=regrown[0]), regrown[1]
        growth.before(kept.maps)
        state = jax.tree.map(jnp.copy, kept)


def _compile_scan(state: rbpf.FilterState, frames: tuple, obs: jax.Array, headings: jax.Array,
                  params: rbpf.FilterParams, cfg: rbpf.FilterConfig) -> None:
    """Compile ``rbpf.scan_frames`` for chunks like ``frames`` from a state shaped like
    ``state`` (shapes only: ``jax.eval_shape``), then return the compiler's freed working
    memory to the system (``release_free_heap``)."""
    keys, controls, obs_index, fallback = frames
    rbpf.scan_frames.lower(state, keys, controls, obs_index, obs, params, cfg, headings,
                           fallback).compile()
    release_free_heap()


def _keep_chunk(kept: tuple | None, out: tuple, start: int, frames: int) -> tuple:
    """Copy one chunk's per-frame outputs (``out``, on the host) into ``kept``, arrays of
    ``frames`` frames allocated at the first chunk: the run's outputs are held once, not once
    per chunk and again when joined."""
    if kept is None:
        kept = jax.tree.map(lambda x: np.empty((frames,) + x.shape[1:], x.dtype), out)
    for whole, part in zip(jax.tree.leaves(kept), jax.tree.leaves(out)):
        whole[start:start + len(part)] = part
    return kept


def run_slam(run: Run, config: Config, progress: Callable[[int, int], None] | None = None,
             chunk: int = 512, key: jax.Array | None = None,
             prior: PriorMap | None = None,
             on_chunk: Callable[[ChunkReport], None] | None = None) -> SlamResult:
    """Run the filter over a whole Run in chunks of frames (same numbers as one scan).

    Chunking bounds the per-frame outputs held on device and lets ``progress(done, total)``
    and ``on_chunk(ChunkReport)`` (e.g. ``app.viewer``) report; the per-frame PRNG keys are
    fixed up front, so results do not depend on ``chunk``.
    Raises ConfigError when the particle maps would not fit in memory (before allocating
    them), RunError when a local map's observation is not finite in float32
    (``local_observations``) and WeightError, naming the first frame and its local map, when
    an update leaves non-finite weights (``chunk_checks``).

    Map reuse: with a ``prior`` map (``PriorMap``) every particle starts with it, at
    ``prior.start`` (spread by ``prior.start_sigma``), and extends it; the results (paths,
    ``vo_path``, map) are in the prior's frame, on its lattice (``filter_config``).

    The filter runs on the map lattice's axes (``map_heading``); the paths are turned back
    into the run's frame and the map keeps its axes (``SlamResult.map_heading``). A prior's
    start spread is drawn on its lattice's axes. The trajectories through the particles'
    ancestry are built when first read (``results.PathEstimates``). An ArgumentError names a
    ``run``, ``config`` or ``chunk`` of the wrong type.
    """
    if not isinstance(run, Run):
        raise ArgumentError(f"run_slam: run must be a gslam_jax.Run (load_run(path), "
                            f"simulate_run(...)[0]), got {type(run).__name__}")
    if not isinstance(config, Config):
        raise ArgumentError(f"run_slam: config must be a gslam_jax.Config (Config(), or "
                            f"load_config(path)), got {type(config).__name__}")
    integer_argument(chunk, "run_slam: chunk", 1)
    given, heading, run = filtered_run(run, config, prior)
    check_local_lattices(given, heading)
    cfg = filter_config(config, run, prior)
    params = filter_params(config, run)
    obs = map_observations(run, config)
    headings = jnp.asarray(run.lattice_heading_array())
    T = run.num_frames
    key = jax.random.key(config.filter.seed) if key is None else key
    keys = rbpf.frame_keys(key, T)
    controls = np.asarray(run.controls, np.float32)
    obs_index = np.asarray(run.obs_index, np.int32)
    chunk = max(1, min(chunk, T))
    pad = (-T) % chunk
    controls = np.concatenate([controls, np.zeros((pad, 3), np.float32)])
    obs_index = np.concatenate([obs_index, -np.ones(pad, np.int32)])
    fallback = fallback_frames(run, config)
    if fallback is not None:
        fallback = np.concatenate([fallback, np.zeros(pad, bool)])
    keys = jnp.concatenate([keys, jax.random.split(jax.random.key(0), pad)]) if pad else keys

    def chunk_frames(start: int) -> tuple:
        sl = slice(start, start + chunk)
        return (keys[sl], jnp.asarray(controls[sl]), jnp.asarray(obs_index[sl]),
                None if fallback is None else jnp.asarray(fallback[sl]))

    t0 = time.perf_counter()
    start_pose = jnp.asarray(run.start_pose(), jnp.float32)
    if prior is None:
        # Compiled before the particles' maps exist: the compiler's working memory is freed
        # and handed back before the maps are allocated, so it never adds to them (the first
        # chunk's call finds the compiled scan).
        _compile_scan(jax.eval_shape(lambda pose: rbpf.init(cfg, pose), start_pose),
                      chunk_frames(0), obs, headings, params, cfg)
        state = rbpf.init(cfg, start_pose)
    else:
        state = prior_state(prior._replace(start=run.start_pose()), cfg, key)
    kept = None
    available, what = map_memory()
    # an automatic pool keeps a copy of each chunk's start to run it again if it runs out:
    # two pools live at once, so each may take half the memory
    growth = maps.PoolGrowth.automatic(cfg, config.map.pool_tiles, available // 2, what)
    compile_s = hook_s = 0.0
    for start in range(0, T + pad, chunk):
        state, out, cfg = _scan_chunk(state, start, chunk_frames(start), obs, headings,
                                      params, cfg, growth)
        if start == 0:  # the compilation and the first chunk
            compile_s = time.perf_counter() - t0
            if prior is not None:  # the first chunk compiled the scan
                release_free_heap()
        check_weights(out[0], start, min(chunk, T - start), obs_index)
        check_map_status(out[0], start, cfg, automatic=growth is not None)
        kept = _keep_chunk(kept, out, start, T + pad)
        if on_chunk is not None:  # its time (e.g. a viewer's logging) is not the filter's
            h0, n = time.perf_counter(), min(chunk, T - start)
            on_chunk(ChunkReport(run, start, jax.tree.map(lambda x: x[:n], out[0]),
                                 out[1][:n], out[2][:n], state, cfg, heading))
            hook_s += time.perf_counter() - h0
        if progress is not None:
            progress(min(start + chunk, T), T)
        if growth is not None and start + chunk < T:
            grown, cfg = growth.after(state.maps, cfg, out[0].map_free, start + chunk)
            state = state._replace(maps=grown)
    seconds = time.perf_counter() - t0 - compile_s - hook_s
    infos, best, mean = jax.tree.map(lambda x: x[:T], kept)
    map_slot = rbpf.map_particle(config.filter.estimate, jnp.asarray(infos.pose[-1]),
                                 state.log_w, state.best)
    kmap, smap = rbpf.particle_map(state, map_slot, cfg)
    violations = check_observed_cells(infos, cfg)
    paths = PathEstimates(Ancestry(
        pose=infos.pose, ancestors=infos.ancestors, log_w=state.log_w, best=state.best,
        map_slot=map_slot, step_log_w=infos.log_w, resampled=infos.resampled, mean_pose=mean,
        run=run, heading=heading))
    return SlamResult(
        paths=paths, best_pose=turn_poses(best, heading), mean_pose=turn_poses(mean, heading),
        vo_path=given.vo_poses(),
        ess=infos.ess, resampled=infos.resampled, updated=infos.updated, log_lik=infos.log_lik,
        exponent=infos.exponent, noise_scale=infos.noise_scale, kmap=np.asarray(kmap),
        smap=np.asarray(smap),
        map_origin=cfg.map_origin, resolution=cfg.resolution, extent_violations=violations,
        empty_observations=int(np.sum(infos.empty_obs & infos.updated)), seconds=seconds,
        compile_seconds=compile_s, compile_frames=min(chunk, T), store=cfg.store,
        map_bytes=maps.map_bytes(cfg),
        map_peak_bytes=maps.peak_bytes(state.maps, cfg), estimate=config.filter.estimate,
        map_heading=heading)
