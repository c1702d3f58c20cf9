"""Benchmark of the filter step: microseconds per particle per update (``gslam bench``).

Times ``rbpf.update`` (footprint reads, fused log-gamma weights, scatter-add map update,
normalisation, ESS; no resampling, which is a step of its own, so every update does the same work) the way
``run_filter`` executes it: ``chain`` updates in one ``lax.scan``, so buffers are reused and the
maps are updated in place. Also times ``predict`` per frame and one forced resampling per update
(``densestore.gather_particles``: the maps of the particles left without offspring are overwritten by
their ancestors', over the map rows the updates have written so far; the survivors' maps are not
copied). All after compilation, with the machine and library versions printed beside the figures.
"""

from __future__ import annotations

import itertools
import json
import math
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from gslam_jax import choices, rbpf
from gslam_jax.app.outfile import atomic_file, check_output_file, write_text_atomic
from gslam_jax.driver.machine import environment, physical_memory
from gslam_jax.errors import InputError
from gslam_jax.rbpf import maps, unknown

__all__ = ["BenchError", "bench_config", "synthetic_local_map", "synthetic_state", "chained",
           "check_arguments", "time_update", "time_course", "plot_scaling", "main"]


class BenchError(InputError):
    """A ``gslam bench`` argument the filter cannot run with: the message names the option."""


def bench_config(J: int, local: int, map_side: int, mode: str, particle_block: int = 0,
                  store: str = "dense", updates: int = 1) -> rbpf.FilterConfig:
    """The filter config ``time_update`` times (0.16 m cells, map centred on the origin);
    the window store's history holds ``updates`` local maps."""
    cfg = rbpf.FilterConfig(num_particles=J, map_shape=(map_side, map_side),
                            map_origin=(-0.08 * map_side, -0.08 * map_side), resolution=0.16,
                            local_size=local, unknown_cells=mode,
                            particle_block=particle_block, store=store)
    return maps.resolve_history(cfg, updates)


def synthetic_local_map(rng: np.random.Generator, local: int) -> jax.Array:
    """A local map [L, L, 2] (k, S) with every cell observed: k uniform in 0..29 points, S of
    gamma-distributed variances (what ``time_update`` and the profiling experiments feed)."""
    k = rng.integers(0, 30, (local, local)).astype(np.float32)
    return jnp.asarray(np.stack([k, k * rng.gamma(2.0, 0.01, k.shape).astype(np.float32)], -1))


def check_arguments(particles, local, map_side, modes, particle_block, stores) -> None:
    """BenchError, before any timing, for a combination the filter refuses: a map side that is
    not a multiple of the bitmask block or smaller than a local map's update window, a
    negative particle block, or anything else ``FilterConfig.validate`` rejects."""
    for b in particle_block:
        if b < 0:
            raise BenchError(f"--particle-block {b}: must be >= 0 (0: automatic)")
    for side in map_side:
        if side % unknown.BLOCK:
            raise BenchError(f"--map {side}: must be a multiple of {unknown.BLOCK} cells")
    for L, side in itertools.product(local, map_side):
        window, mode = max((bench_config(1, L, side, m).window, m) for m in modes)
        if side < window:
            raise BenchError(f"--map {side}: smaller than the update window of --local {L} "
                             f"({window} cells with --mode {mode}); use --map {window} or more, "
                             "or a smaller --local")
    for L, side, mode, J, b, store in itertools.product(local, map_side, modes, particles,
                                                        particle_block, stores):
        if store == "window" and mode == "sample":
            raise BenchError("--store window --mode sample: the window store does eq. 30 "
                             "(--mode ignore) only")
        try:
            bench_config(J, L, side, mode, b, store).validate()
        except ValueError as err:
            raise BenchError(f"--particles {J} --local {L} --map {side} --mode {mode} "
                             f"--particle-block {b} --store {store}: {err}") from err

def synthetic_state(cfg: rbpf.FilterConfig, rng: np.random.Generator) -> rbpf.FilterState:
    """Particles scattered around the map centre (1 m standard deviation, any heading) on
    empty maps (``rbpf.init``: every cell unknown); the timed updates fill their footprints."""
    H, W = cfg.map_shape
    state = rbpf.init(cfg)
    centre = np.array([cfg.map_origin[0] + 0.5 * H * cfg.resolution,
                       cfg.map_origin[1] + 0.5 * W * cfg.resolution])
    pose = np.column_stack([centre[0] + rng.normal(0, 1.0, cfg.num_particles),
                            centre[1] + rng.normal(0, 1.0, cfg.num_particles),
                            rng.uniform(-np.pi, np.pi, cfg.num_particles)]).astype(np.float32)
    return state._replace(pose=jnp.asarray(pose))


def chained(fn, chain: int):
    """jit(scan of ``chain`` calls of fn(state) -> state), donating the state."""

    def many(state):
        return lax.scan(lambda s, _: (fn(s), None), state, None, length=chain)[0]

    return jax.jit(many, donate_argnums=0)


def _best_seconds(fn, state, repeats: int):
    """Best wall time of ``repeats`` calls (after one warm-up call); returns (seconds, state)."""
    state = fn(state)
    jax.block_until_ready(state)
    best = math.inf
    for _ in range(repeats):
        t = time.perf_counter()
        state = fn(state)
        jax.block_until_ready(state)
        best = min(best, time.perf_counter() - t)
    return best, state


def time_update(J: int, local: int, map_side: int, mode: str, repeats: int = 10,
                seed: int = 0, chain: int = 10, particle_block: int = 0,
                store: str = "dense") -> dict:
    """Per-update cost for J particles: best of ``repeats`` scans of ``chain`` updates. With
    ``store = "shared"`` the forced resamplings ("resample_ms") include the copy-on-write of
    every footprint's tiles at the next update."""
    rng = np.random.default_rng(seed)
    # every timed call of the update and of the resampling chains ``chain`` updates
    cfg = bench_config(J, local, map_side, mode, particle_block, store,
                       updates=2 * (repeats + 1) * chain)
    obs = synthetic_local_map(rng, local)
    params = rbpf.FilterParams()
    noise = rbpf.update_noise(jax.random.key(seed), cfg)
    u = jnp.asarray([0.2, 0.0, 0.05], jnp.float32)
    eps = rbpf.motion_noise(jax.random.key(seed + 1), cfg)

    update = chained(lambda s: rbpf.update(s, obs, noise.unknown_u, params, cfg)[0], chain)
    sec, state = _best_seconds(update, synthetic_state(cfg, rng), repeats)
    predict = chained(lambda s: s._replace(pose=rbpf.predict(s.pose, u, eps, params)), chain)
    sec_predict, state = _best_seconds(predict, state, repeats)
    # The update and one forced resampling (``rbpf.observe``; the dead particles' maps copied
    # from their ancestors over the written rows, ``densestore.gather_particles``), minus the
    # update.
    always = cfg._replace(resample_ratio=2.0)
    resample = chained(lambda s: rbpf.observe(s, obs, noise, params, always)[0], chain)
    sec_resample, state = _best_seconds(resample, state, repeats)
    per = 1.0 / chain
    return {"particles": J, "local": local, "map": map_side, "mode": mode, "store": store,
            "particle_block": cfg.update_block,
            "ms_per_update": 1e3 * sec * per, "us_per_particle": 1e6 * sec * per / J,
            "predict_us_per_particle": 1e6 * sec_predict * per / J,
            "resample_ms": 1e3 * max(sec_resample - sec, 0.0) * per,
            "mb_per_particle": maps.map_bytes(cfg) / J / 1e6}


def time_course(course: str = "mars-yard-a", particles: int = 200, seed: int = 0) -> dict:
    """Whole-course wall time of the filter from a prepared Run (default settings otherwise):
    the first ``run_slam`` compiles, the second is timed. Also the process's peak RSS."""
    import dataclasses
    import resource

    from gslam_jax.config import Config
    from gslam_jax.datasets.sim import simulate_run
    from gslam_jax.driver import sizing, slam
    from gslam_jax.vo.localmap import localmap_params

    config = Config()
    config = dataclasses.replace(config, filter=dataclasses.replace(config.filter,
                                                                    particles=particles))
    run, _ = simulate_run(course, seed=seed, params=localmap_params(config))
    first = time.perf_counter()
    slam.run_slam(run, config)
    first = time.perf_counter() - first
    t = time.perf_counter()
    res = slam.run_slam(run, config)
    wall = time.perf_counter() - t
    cfg = sizing.filter_config(config, run)
    maps_mb = 2 * 4 * particles * cfg.map_shape[0] * cfg.map_shape[1] / 1e6
    return {"course": course, "particles": particles, "frames": run.num_frames,
            "local_maps": run.num_local_maps, "local": cfg.local_size,
            "map": list(cfg.map_shape), "wall_s": wall, "first_call_s": first,
            "resamples": int(res.resampled.sum()), "maps_mb": maps_mb,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3}


def _plot_file(path: str | Path) -> Path:
    """The file a plot is written to: ``path``, with ".png" added when it has no suffix (as
    matplotlib adds it)."""
    path = Path(path)
    return path if path.suffix else path.with_name(path.name + ".png")


def plot_scaling(rows: list[dict], path: Path) -> None:
    """us per particle per update against J, one line per (mode, local, map, block setting)."""
    from gslam_jax.app.plots import plt

    def line(r):
        return r["mode"], r["local"], r["map"], r.get("block_setting", 0), r.get("store", "dense")

    fig, ax = plt.subplots(figsize=(6, 4))
    for key in sorted({line(r) for r in rows}):
        pts = sorted((r["particles"], r["us_per_particle"]) for r in rows if line(r) == key)
        block = f", block {key[3]}" if key[3] else ""
        block += f", {key[4]} store" if key[4] != "dense" else ""
        ax.plot(*zip(*pts), marker="o", label=f"{key[0]}, local {key[1]}, map {key[2]}{block}")
    ax.set_xscale("log")
    ax.set_xlabel("particles J")
    ax.set_ylabel("us per particle per update")
    ax.set_ylim(bottom=0)
    ax.legend(fontsize=7)
    fig.tight_layout()
    with atomic_file(_plot_file(path), "--plot") as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)


def main(particles=(50, 200, 1000), local=(64,), map_side=(640,), repeats: int = 10,
         modes=choices.UNKNOWN_CELLS, json_path: Path | None = None, course: str | None = None,
         course_particles: int = 200, plot_path: Path | None = None,
         particle_block=(0,), stores=("dense",), overwrite: bool = False) -> int:
    """Print (and optionally save) the update cost over every combination of the arguments.

    The cost should be flat in the map size (each update touches one footprint per particle) and
    linear in J; the last column divides by J so both are easy to read off. ``particle_block``
    (0: automatic) takes several values to compare block sizes in one process. The arguments
    and the output paths are checked before any timing (``check_arguments``,
    ``check_output_file``: an existing file only with ``overwrite``); the outputs are written
    atomically.
    """
    particle_block = [particle_block] if isinstance(particle_block, int) else list(particle_block)
    local = [local] if isinstance(local, int) else list(local)
    map_side = [map_side] if isinstance(map_side, int) else list(map_side)
    check_arguments(particles, local, map_side, modes, particle_block, stores)
    if json_path:
        check_output_file(json_path, "--json", overwrite)
    if plot_path:
        check_output_file(_plot_file(plot_path), "--plot", overwrite)
    env = environment()
    print("gslam bench: local-map update (footprint reads + fused log-gamma weights + scatter-add"
          " map update + normalise), chained in a lax.scan as runs execute it")
    for k, v in env.items():
        print(f"  {k}: {v}")
    rows = []
    print(f"{'mode':>7} {'store':>7} {'J':>6} {'local':>6} {'map':>6} {'block':>6} {'ms/update':>10} {'us/particle':>12} "
          f"{'predict us/p':>13} {'resample ms':>12} {'MB/particle':>12}")
    for mode in modes:
        for L in local:
            for side in map_side:
                for J, block, store in itertools.product(particles, particle_block, stores):
                    need = 2 * 4 * J * side * side if store == "dense" else 0
                    if need > 0.5 * physical_memory():
                        print(f"{mode:>7} {store:>7} {J:>6} {L:>6} {side:>6}   skipped: the maps need "
                              f"{need / 1e9:.1f} GB, over half of this machine's memory")
                        continue
                    r = time_update(J, L, side, mode, repeats, particle_block=block,
                                    store=store)
                    r["block_setting"] = block
                    rows.append(r)
                    print(f"{mode:>7} {store:>7} {J:>6} {L:>6} {side:>6} {r['particle_block']:>6} "
                          f"{r['ms_per_update']:>10.2f} "
                          f"{r['us_per_particle']:>12.1f} {r['predict_us_per_particle']:>13.3f} "
                          f"{r['resample_ms']:>12.1f} {r['mb_per_particle']:>12.2f}", flush=True)
    result = {"environment": env, "results": rows}
    if course:
        c = time_course(course, course_particles)
        result["course"] = c
        print(f"{course}, J = {c['particles']}, {c['frames']} frames, {c['local_maps']} local maps "
              f"({c['local']}^2 cells), map {c['map'][0]} x {c['map'][1]}: {c['wall_s']:.2f} s "
              f"after compilation ({c['first_call_s']:.1f} s with it), {c['resamples']} "
              f"resamplings; maps {c['maps_mb']:.0f} MB, process peak RSS {c['peak_rss_mb']:.0f} MB")
    if plot_path:
        plot_scaling(rows, Path(plot_path))
    if json_path:
        write_text_atomic(json_path, json.dumps(result, indent=2), "--json")
    return 0
