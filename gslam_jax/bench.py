"""Benchmark of the local-map update: microseconds per particle per update (``gslam bench``).

Times ``filter.update`` alone (map window update, fused log-gamma weights, normalisation, ESS;
resampling disabled so every repeat does the same work), after compilation, with the machine
and library versions printed beside the figures.
"""

from __future__ import annotations

import json
import os
import platform
import time
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from gslam_jax import filter as gf

__all__ = ["environment", "time_update", "main"]


def environment() -> dict:
    """Machine and versions, printed beside every figure this project reports."""
    import cv2
    import optax

    return {
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "machine": platform.machine(),
        "processor": platform.processor() or platform.uname().machine,
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "jaxlib": jax.lib.__version__ if hasattr(jax.lib, "__version__") else "",
        "numpy": np.__version__,
        "opencv": cv2.__version__,
        "optax": optax.__version__,
        "backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
    }


def _synthetic_state(cfg: gf.FilterConfig, rng: np.random.Generator) -> gf.FilterState:
    """Particles scattered around the map centre over a half-known map."""
    H, W = cfg.map_shape
    state = gf.init(cfg)
    centre = np.array([cfg.map_origin[0] + 0.5 * H * cfg.resolution,
                       cfg.map_origin[1] + 0.5 * W * cfg.resolution])
    pose = np.column_stack([centre[0] + rng.normal(0, 1.0, cfg.num_particles),
                            centre[1] + rng.normal(0, 1.0, cfg.num_particles),
                            rng.uniform(-np.pi, np.pi, cfg.num_particles)]).astype(np.float32)
    return state._replace(pose=jnp.asarray(pose))


def time_update(J: int, local: int, map_side: int, mode: str, repeats: int = 10,
                seed: int = 0) -> dict:
    """Seconds per update (median of ``repeats``) for J particles, after a warm-up update."""
    rng = np.random.default_rng(seed)
    cfg = gf.FilterConfig(num_particles=J, map_shape=(map_side, map_side),
                          map_origin=(-0.08 * map_side, -0.08 * map_side), resolution=0.16,
                          local_size=local, unknown_cells=mode, resample_ratio=0.0)
    k = rng.integers(0, 30, (local, local)).astype(np.float32)
    obs = jnp.asarray(np.stack([k, k * rng.gamma(2.0, 0.01, k.shape).astype(np.float32)], -1))
    params = gf.FilterParams()
    fn = jax.jit(partial(gf.update, cfg=cfg), donate_argnums=0)
    state = _synthetic_state(cfg, rng)
    noise = gf.update_noise(jax.random.key(seed), cfg)
    state, info = fn(state, obs, noise, params)  # compile, and make the maps half-known
    jax.block_until_ready(state)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        state, info = fn(state, obs, noise, params)
        jax.block_until_ready((state, info))
        times.append(time.perf_counter() - t)
    sec = float(np.median(times))
    return {"particles": J, "local": local, "map": map_side, "mode": mode, "window": cfg.window,
            "ms_per_update": 1e3 * sec, "us_per_particle": 1e6 * sec / J}


def main(particles=(50, 200, 1000), local=(64,), map_side=(640,), repeats: int = 10,
         modes=("ignore", "sample"), json_path: Path | None = None) -> int:
    """Print (and optionally save) the update cost over every combination of the arguments.

    The cost should be flat in the map size (each update touches one window per particle) and
    linear in J; the last column divides by J so both are easy to read off.
    """
    local = [local] if isinstance(local, int) else list(local)
    map_side = [map_side] if isinstance(map_side, int) else list(map_side)
    env = environment()
    print("gslam bench: local-map update (window update + fused log-gamma weights + normalise)")
    for k, v in env.items():
        print(f"  {k}: {v}")
    rows = []
    print(f"{'mode':>7} {'J':>6} {'local':>6} {'map':>6} {'window':>7} {'ms/update':>10} "
          f"{'us/particle':>12} {'MB/particle':>12}")
    for mode in modes:
        for L in local:
            for side in map_side:
                for J in particles:
                    r = time_update(J, L, side, mode, repeats)
                    r["mb_per_particle"] = 2 * 4 * side * side / 1e6
                    rows.append(r)
                    print(f"{mode:>7} {J:>6} {L:>6} {side:>6} {r['window']:>7} "
                          f"{r['ms_per_update']:>10.2f} {r['us_per_particle']:>12.1f} "
                          f"{r['mb_per_particle']:>12.2f}", flush=True)
    if json_path:
        Path(json_path).write_text(json.dumps({"environment": env, "results": rows}, indent=2))
    return 0
