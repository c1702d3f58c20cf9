"""Dense JAX filter vs tiled copy-on-write reference: agreement, time and memory
(``gslam compare``).

Both filters run the same Run with the same per-frame random numbers. Agreement is checked per
frame (log weights, poses), on resampling decisions, and on the final maps (k, S). Exact
agreement of the discrete choices (which cell a local cell lands in) needs the dense filter
compiled without fused multiply-adds: set ``XLA_FLAGS=--xla_cpu_max_isa=AVX`` before JAX starts
(``experiments/compare_tiled.py --exact``); with FMA a few boundary cells may land differently.
The dense timings are then those of that AVX-only build, and are labelled so.

Timing: the dense run is timed after compilation; the tiled run after its random numbers were
drawn (``reference.draw_noise``: jitted, then copied to NumPy), so neither total includes
compilation or JAX dispatch of the draws; the draws' time is reported on its own.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import time
from pathlib import Path

import jax
import numpy as np

from gslam_jax import rbpf
from gslam_jax.app.dense_timing import DenseOutput, run_dense
from gslam_jax.app.results import results_folder
from gslam_jax.config import Config, ConfigError
from gslam_jax.errors import InputError
from gslam_jax.rbpf import maps
from gslam_jax.run import Run
from gslam_jax.tiled.reference import (
    DEFAULT_TILE_SIZE,
    Decisions,
    TiledOutput,
    draw_noise,
    run_tiled,
)
from gslam_jax.vo.localmap import LocalMapParams

__all__ = ["TOLERANCES", "MAX_TILE_CELLS", "CompareError", "default_resolution",
           "default_tile_size", "check_tile_size", "dense_label", "check_agreement",
           "default_run", "compare"]

TOLERANCES = {"log_w": 1e-4, "pose": 1e-5, "k": 1e-6, "S_rel": 1e-5}

# Most cells per side of a tile: the paper's 10 m tiles are 62 cells at 0.16 m; one tile of
# 4096 x 4096 cells holds 128 MB of (k, S) and is copied whole on a particle's first write.
MAX_TILE_CELLS = 4096


class CompareError(InputError):
    """A ``gslam compare`` option the comparison cannot run with: the message names it."""


def check_tile_size(tile_size: float, resolution: float,
                    map_shape: tuple[int, int] | None = None) -> int:
    """The tile side in cells of ``--tile-size`` (metres); CompareError, before any work, when
    it is under one cell, not a whole number of cells (with the two nearest sizes that are),
    over ``MAX_TILE_CELLS`` or, when ``map_shape`` is given, wider than the map."""
    name = f"--tile-size {tile_size:g}"
    n = tile_size / resolution
    if not math.isfinite(n):
        raise CompareError(f"{name} m is not a usable tile size at resolution {resolution:g} m")
    if n < 1.0 - 1e-6:
        raise CompareError(f"{name} m is under one cell at resolution {resolution:g} m; use "
                           f"{resolution:.6g} m (1 cell) or a whole number of cells more")
    if n > MAX_TILE_CELLS:
        raise CompareError(f"{name} m is {n:.4g} cells per side at resolution {resolution:g} m, "
                           f"more than {MAX_TILE_CELLS}; use at most "
                           f"{MAX_TILE_CELLS * resolution:.6g} m (the paper's tiles are 10 m)")
    side = round(n)
    if abs(n - side) > 1e-6 * max(1.0, n):  # the tolerance of tiled.tiles.tile_cells
        lo = math.floor(n)
        raise CompareError(f"{name} m is {n:.4g} cells at resolution {resolution:g} m, not a "
                           f"whole number of cells; use e.g. {lo * resolution:.6g} m ({lo} "
                           f"cells) or {(lo + 1) * resolution:.6g} m ({lo + 1} cells)")
    if map_shape is not None and side > max(map_shape):
        raise CompareError(f"{name} m is {side} cells per side, wider than the map "
                           f"({map_shape[0]} x {map_shape[1]} cells at {resolution:g} m); use "
                           f"at most {max(map_shape) * resolution:.6g} m")
    return int(side)


def default_resolution() -> float:
    """The cell side (metres) of the Run ``compare`` simulates when given none."""
    return DEFAULT_RUN_PARAMS.resolution


def default_tile_size(resolution: float, metres: float = DEFAULT_TILE_SIZE) -> float:
    """The whole number of cells nearest the paper's 10 m, in metres."""
    return max(1, round(metres / resolution)) * resolution


def _max_isa(xla_flags: str | None = None) -> str | None:
    """The ISA cap ``--xla_cpu_max_isa=...`` in ``xla_flags`` (default: $XLA_FLAGS), if any."""
    flags = os.environ.get("XLA_FLAGS", "") if xla_flags is None else xla_flags
    isa = re.findall(r"--xla_cpu_max_isa=(\S+)", flags)
    return isa[-1] if isa else None


def dense_label(xla_flags: str | None = None, store: str = "dense") -> str:
    """Column label of the JAX filter: "dense (JAX)", or "dense (JAX, AVX only)" when
    ``xla_flags`` (default: $XLA_FLAGS) caps the ISA at AVX, as ``--exact`` does; "shared"
    for the shared-tile store."""
    isa = _max_isa(xla_flags)
    return f"{store} (JAX, {isa} only)" if isa else f"{store} (JAX)"


def _mean(x: np.ndarray) -> float:
    return float(np.mean(x)) if len(x) else float("nan")


def check_agreement(dense: DenseOutput, tiled: TiledOutput, cfg: rbpf.FilterConfig) -> dict:
    """Largest differences per quantity and whether each is within ``TOLERANCES``.

    Also reports where the two runs part: the first frame whose resampling decision,
    ancestors or poses differ (``diverged_at``, None if never); the ``*_before`` figures
    compare the frames before that point. Where the two differ only by rounding (an ESS within
    rounding of the threshold, a draw within float32 rounding of a cumulative-weight boundary:
    the dense filter works in float32, the reference in float64), the reference, given the
    dense decisions (``run_tiled(follow=...)``), takes them: those frames are counted and
    listed (``rounding_events``, ``rounding``), and "ok" means agreement apart from them.
    """
    H, W = cfg.map_shape
    km = np.stack([m.dense((H, W))[0] for m in tiled.final.maps])
    sm = np.stack([m.dense((H, W))[1] for m in tiled.final.maps])
    pose_err = np.max(np.abs(dense.pose - tiled.pose), axis=(1, 2))
    logw_err = np.max(np.abs(dense.log_w - tiled.log_w), axis=1)
    anc_differ = np.zeros(len(pose_err), bool)
    if dense.ancestors is not None:
        anc_differ = np.any(np.asarray(dense.ancestors) != tiled.ancestors, axis=1)
    parted = (dense.resampled != tiled.resampled) | anc_differ | (pose_err > 1e-3)
    first = int(np.argmax(parted)) if parted.any() else None
    before = slice(0, first)
    d = {
        "log_w": float(np.max(logw_err)),
        "pose": float(np.max(pose_err)),
        "k": float(np.max(np.abs(dense.kmap - km))),
        "S_rel": float(np.max(np.abs(dense.smap - sm) / np.maximum(np.abs(dense.smap), 1e-6))),
        "resampling_mismatches": int(np.sum(dense.resampled != tiled.resampled)),
        "resampling_events": int(np.sum(dense.resampled)),
        "ancestor_mismatches": int(np.sum(anc_differ)),
        "rounding_events": len(tiled.rounding),
        "rounding": [{"frame": r.frame, "kind": r.kind, "moved": r.moved,
                      ("ess" if r.kind == "decision" else "largest_gap"): r.value}
                     for r in tiled.rounding],
        "diverged_at": first,
        "frames": int(len(pose_err)),
        "log_w_before": float(np.max(logw_err[before], initial=0.0)),
        "pose_before": float(np.max(pose_err[before], initial=0.0)),
    }
    d["ok"] = bool(all(d[n] <= tol for n, tol in TOLERANCES.items())
                   and not d["resampling_mismatches"] and not d["ancestor_mismatches"])
    return d


def _rounding_text(event: dict) -> str:
    """One rounding event for the console."""
    if event["kind"] == "decision":
        return f"frame {event['frame']}: resampling decision at ESS {event['ess']:.6g}"
    return (f"frame {event['frame']}: {event['moved']} ancestor draw(s), at most "
            f"{event['largest_gap']:.2g} from a cumulative-weight boundary")


def _plot(path: Path, dense: DenseOutput, tiled: TiledOutput, title: str) -> None:
    """Paper Fig. 4 style: ESS and map memory over frames."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    a.plot(dense.ess, label=dense_label())
    a.plot(tiled.ess, "--", label="tiled reference")
    a.set_ylabel("effective sample size")
    a.legend()
    b.plot(tiled.memory_bytes / 2 ** 20, label="tiled: bytes held by tiles (and known caches)")
    b.axhline(dense.state_bytes / 2 ** 20, color="k", ls=":", label="dense: state arrays (fixed)")
    b.set_ylabel("map memory (MB)")
    b.set_xlabel("frame")
    b.set_yscale("log")
    b.legend()
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# The local maps of the default run: a 5 m range, one every 2 m of travel.
DEFAULT_RUN_PARAMS = LocalMapParams(max_range=5.0, travel=2.0)


def default_run() -> Run:
    """The run ``compare`` uses when given none: the simulated mars-yard-a course, seed 0, its
    first 600 frames, local maps of ``DEFAULT_RUN_PARAMS``."""
    from gslam_jax.datasets.sim import simulate_run

    run, _ = simulate_run("mars-yard-a", seed=0, params=DEFAULT_RUN_PARAMS, max_frames=600)
    return run


def compare(run: Run | None = None, config: Config | None = None, *, particles: int = 200,
            unknown_cells: str | None = None, tile_size: float | None = None, seed: int = 0,
            out_dir: str | Path | None = None, verbose: bool = True, store: str | None = None,
            pool_tiles: int | None = None, overwrite: bool = False) -> dict:
    """Run the dense and the tiled filter on ``run`` (default: a simulated course) with the same
    random numbers; check agreement; print time and memory side by side.

    Returns a dict with ``agreement``, timings, memory figures, per-frame memory and ESS; writes
    ``compare.json`` and ``compare_fig4.png`` into the results folder ``out_dir`` when given
    (``results.results_folder``: staged, renamed into place when complete; an existing,
    non-empty folder is refused unless ``overwrite``). The options and ``out_dir`` are checked
    before any work (CompareError, ResultsError).
    """
    say = print if verbose else (lambda *a, **k: None)
    resolution = run.resolution if run is not None else default_resolution()
    if tile_size is not None:
        check_tile_size(tile_size, resolution)
    if pool_tiles is not None and pool_tiles < 0:
        raise CompareError(f"--pool-tiles {pool_tiles}: must be >= 0 (0: automatic)")
    options = dict(particles=particles, unknown_cells=unknown_cells, tile_size=tile_size,
                   seed=seed, store=store, pool_tiles=pool_tiles)
    if out_dir is None:
        return _compare(run, config, say, **options)[0]
    with results_folder(out_dir, "compare", overwrite=overwrite,
                        command="gslam compare") as folder:
        res, dense, tiled, cfg = _compare(run, config, say, **options)
        (folder.staging / "compare.json").write_text(json.dumps(res, indent=1))
        _plot(folder.staging / "compare_fig4.png", dense, tiled,
              f"J={cfg.num_particles}, {cfg.unknown_cells}: ESS and memory over frames")
    say(f"wrote {folder.target / 'compare.json'} and {folder.target / 'compare_fig4.png'}")
    return res


def _compare(run: Run | None, config: Config | None, say, *, particles: int,
             unknown_cells: str | None, tile_size: float | None, seed: int, store: str | None,
             pool_tiles: int | None) -> tuple[dict, DenseOutput, TiledOutput, rbpf.FilterConfig]:
    """``compare`` without the output folder: the result dict, both runs and the config."""
    from gslam_jax.driver.machine import environment
    from gslam_jax.driver.map_axes import map_heading, on_map_axes
    from gslam_jax.driver.observations import local_observations
    from gslam_jax.driver.sizing import fallback_frames, filter_config, filter_params

    config = config or Config()
    if config.filter.range_noise != "none":
        raise ConfigError(f"[filter] range_noise = \"{config.filter.range_noise}\": the tiled "
                          f"reference implements eq. 26 as the paper has it; compare with "
                          f"range_noise = \"none\"")
    if config.motion.noise_spread != 1:
        raise ConfigError(f"[motion] noise_spread = {config.motion.noise_spread:g}: the tiled "
                          f"reference moves every particle with the same motion noise, as the "
                          f"paper does; compare with noise_spread = 1")
    run = run if run is not None else default_run()
    # both implementations on the map lattice's axes, as ``gslam run`` filters ([map] axes)
    run = on_map_axes(run, map_heading(run, config))
    config = dataclasses.replace(
        config,
        filter=dataclasses.replace(config.filter, particles=particles,
                                   unknown_cells=unknown_cells or config.filter.unknown_cells),
        map=dataclasses.replace(config.map, resolution=run.resolution,
                                store=store or config.map.store,
                                pool_tiles=config.map.pool_tiles if pool_tiles is None
                                else pool_tiles))
    cfg = filter_config(config, run)
    params = filter_params(config)
    obs = local_observations(run, config.map.min_variance)
    if tile_size is not None:
        check_tile_size(tile_size, cfg.resolution, cfg.map_shape)
    tile = tile_size if tile_size is not None else default_tile_size(cfg.resolution)
    key = jax.random.key(seed)
    env = environment()
    say("gslam compare: dense JAX filter vs tiled copy-on-write reference")
    for k, v in env.items():
        say(f"  {k}: {v}")
    say(f"  run: {run.num_frames} frames, {run.num_local_maps} local maps "
        f"({obs.shape[1]}x{obs.shape[1]} cells), map {cfg.map_shape} cells at {cfg.resolution} m, "
        f"J={cfg.num_particles}, unknown_cells={cfg.unknown_cells}, tile {tile:g} m")
    fallback = fallback_frames(run, config)  # the fallback odometry's frames
    dense = run_dense(key, params, run, obs, cfg, fallback=fallback)
    # the reference takes each frame's noise scale as plain numbers
    scale = (None if fallback is None
             else np.where(fallback, config.motion.fallback_scale, 1.0))
    t0 = time.perf_counter()
    draws = draw_noise(key, run.obs_index, cfg)  # compiles and dispatches the draws: not timed
    draw_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    tiled = run_tiled(key, params, run.controls, run.obs_index, obs, cfg, tile, run.start_pose(),
                      draws=draws, follow=Decisions(np.asarray(dense.resampled),
                                                    np.asarray(dense.ancestors)),
                      lattice_headings=run.lattice_heading_array(), noise_scale=scale)
    tiled_s = time.perf_counter() - t0
    agree = check_agreement(dense, tiled, cfg)
    tiled_upd_rs = np.asarray(tiled.resampled)[np.asarray(run.obs_index) >= 0]  # [M]
    upd_t = float(np.mean(tiled.update_seconds))
    tiled_rs = _mean(tiled.update_seconds[tiled_upd_rs])
    tiled_kept = _mean(tiled.update_seconds[~tiled_upd_rs])
    dense_t = float(np.mean(dense.run_update_seconds))
    dense_rs = _mean(dense.run_update_seconds[dense.run_resampled])
    dense_kept = _mean(dense.run_update_seconds[~dense.run_resampled])
    n_resampled = int(np.sum(dense.run_resampled))
    label = dense_label(store=cfg.store)
    MB = 2 ** 20
    res = {
        "environment": env, "particles": cfg.num_particles, "unknown_cells": cfg.unknown_cells,
        "map_shape": list(cfg.map_shape), "tile_size_m": tile, "frames": run.num_frames,
        "updates": run.num_local_maps, "agreement": agree,
        "dense": {"label": label, "xla_cpu_max_isa": _max_isa(),
                  "seconds_per_update": dense_t, "update_alone_seconds": dense.update_seconds,
                  "replay_resamplings": n_resampled,
                  "seconds_per_update_that_resampled": dense_rs,
                  "seconds_per_update_without_resampling": dense_kept,
                  "total_seconds": dense.seconds,
                  # fixed-shape arrays allocated once: the same bytes at every frame
                  "state_MB": dense.state_bytes / MB, "store": cfg.store,
                  # shared store: the most its live tiles (and page tables) held at once
                  "peak_live_MB": dense.live_bytes / MB,
                  "pool_tiles": maps.pool_tiles(cfg) if cfg.store == "shared" else None},
        "tiled": {"seconds_per_update": upd_t,
                  "seconds_per_update_that_resampled": tiled_rs,
                  "seconds_per_update_without_resampling": tiled_kept,
                  "total_seconds": tiled_s, "draw_seconds": draw_s,
                  "peak_MB": tiled.peak_bytes / MB, "final_MB": float(tiled.memory_bytes[-1]) / MB,
                  "final_known_cache_MB": tiled.final.ledger.cache_bytes / MB,
                  "max_tiles": int(tiled.tiles.max()),
                  "max_shared_per_particle": float(tiled.shared_mean.max())},
        "tiled_resamplings": int(np.sum(tiled.resampled)),
        # mean time per local-map update as each run executes it, resampling included
        "speed_ratio_tiled_over_dense": upd_t / dense_t,
        # tiled updates that did not resample against the dense update alone (no resampling)
        "speed_ratio_update_alone": tiled_kept / dense.update_seconds,
        "memory_MB_per_frame": (tiled.memory_bytes / MB).tolist(),
        "ess_dense": np.asarray(dense.ess).tolist(), "ess_tiled": tiled.ess.tolist(),
    }
    w = max(16, len(label) + 2)
    say(f"\n{'':30}{label:>{w}}{'tiled (NumPy)':>16}")
    say(f"{'time per local-map update':30}{1e3 * dense_t:>{w - 3}.2f} ms{1e3 * upd_t:>13.2f} ms"
        f"   (mean over the run's updates, resampling included: {n_resampled} / "
        f"{res['tiled_resamplings']} of {len(dense.run_update_seconds)})")
    say(f"{'  updates that resampled':30}{1e3 * dense_rs:>{w - 3}.2f} ms{1e3 * tiled_rs:>13.2f} ms"
        f"   (dense: copies the dead particles' maps; tiled: shares their tiles)")
    say(f"{'  updates without resampling':30}{1e3 * dense_kept:>{w - 3}.2f} ms"
        f"{1e3 * tiled_kept:>13.2f} ms")
    say(f"{'  update alone, no resampling':30}{1e3 * dense.update_seconds:>{w - 3}.2f} ms"
        f"{'':16}   (dense: final maps, median of repeats, as gslam bench)")
    say(f"{'total time':30}{dense.seconds:>{w - 2}.2f} s{tiled_s:>14.2f} s"
        f"   (both after compilation; tiled draws made beforehand, {draw_s:.2f} s, not counted)")
    if cfg.store == "shared":
        say(f"{'map memory: peak live tiles':30}{dense.live_bytes / MB:>{w - 3}.1f} MB"
            f"{tiled.peak_bytes / MB:>13.1f} MB   (shared: most bytes held by live pool tiles, "
            f"page tables and bookkeeping; its pool of {maps.pool_tiles(cfg)} tiles allocates "
            f"{dense.state_bytes / MB:.1f} MB up front)")
    say(f"{'map memory: fixed / peak':30}{dense.state_bytes / MB:>{w - 3}.1f} MB"
        f"{tiled.peak_bytes / MB:>13.1f} MB"
        f"   (dense: fixed state arrays, the same at every frame; tiled: peak held by tiles"
        + (f" and their known-cell caches ({tiled.final.ledger.cache_bytes / MB:.1f} MB of caches"
           f" at the end)" if cfg.unknown_cells == "sample" else "")
        + "; paper Fig. 4: 40-160 MB for 200 particles)")
    say(f"speed ratio (tiled / {cfg.store} time per update): "
        f"{res['speed_ratio_tiled_over_dense']:.1f}x (tiled updates without resampling / "
        f"{cfg.store} update alone: "
        f"{res['speed_ratio_update_alone']:.1f}x)")
    step = max(1, run.num_frames // 10)
    say("memory over frames (tiled MB / distinct tiles / tiles shared per particle):")
    for t in range(0, run.num_frames, step):
        say(f"  frame {t:5d}: {tiled.memory_bytes[t] / MB:8.2f} MB {tiled.tiles[t]:7d} "
            f"{tiled.shared_mean[t]:7.1f}   ESS {float(dense.ess[t]):7.1f}")
    say(f"agreement: {json.dumps({k: v for k, v in agree.items() if k != 'rounding'})}")
    if agree["rounding"]:
        say(f"rounding events: {len(agree['rounding'])}, where the reference took the dense "
            "filter's choice because the two differed only within rounding (float32 against "
            "float64): " + "; ".join(_rounding_text(r) for r in agree["rounding"]))
    say(f"verdict: {'ok' if agree['ok'] else 'FAILED'}"
        + (f" (apart from {agree['rounding_events']} counted rounding events)"
           if agree["rounding_events"] else "")
        + ("" if agree["ok"] or agree["diverged_at"] is None
           else f"; the runs part at frame {agree['diverged_at']}"))
    return res, dense, tiled, cfg
