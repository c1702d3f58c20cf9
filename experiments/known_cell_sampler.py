"""What eq. 31's known-cell sampler costs per particle and update: the segment counts each store
keeps (``maps.sample_known``: ``densestore.sample_known``, ``tilesample.sample_known``) against
the whole-map scan they replaced (every particle's bits gathered, ``unknown.sample_known_cells``),
in one process on synthetic maps, and that both give the same cells.

    python -m experiments.known_cell_sampler --map 1984 2240 --particles 100 \
        --density 0.05 0.3 --samples 1024

Each map is a random known-cell mask of the given density (k > 0), the same in every particle
(``maps.init`` with a prior map: the dense store copies it, the shared store holds its tiles
once). Prints the machine and versions, microseconds per particle (best of --repeats) and the
ratio of the two samplers on each store.
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

from gslam_jax import rbpf
from gslam_jax.driver.machine import environment
from gslam_jax.rbpf import maps, unknown


def _best(fn, args, repeats: int) -> float:
    jax.block_until_ready(fn(*args))  # compile
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t)
    return min(times)


def _whole_map(store: maps.Maps, rows: jax.Array, u: jax.Array, cfg) -> tuple:
    """The scan the stores no longer do: each particle's whole-map bits, then
    ``unknown.sample_known_cells``."""
    bits = maps.known_bits(store, rows, cfg)
    return jax.vmap(unknown.sample_known_cells)(bits, u)


def measure(shape: tuple[int, int], J: int, density: float, samples: int, store: str,
            repeats: int, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    k = np.where(rng.random(shape) < density, 3.0, 0.0).astype(np.float32)
    cfg = rbpf.FilterConfig(J, shape, (0.0, 0.0), 0.16, 64, unknown_cells="sample",
                            store=store)
    cfg = cfg._replace(pool_tiles=maps.whole_maps_tiles(cfg, 1))  # the prior map's tiles, once
    store_ = maps.init(cfg, (jnp.asarray(k), jnp.asarray(k * 1e-3)))
    rows = jnp.arange(J, dtype=jnp.int32)
    u = jax.random.uniform(jax.random.key(seed), (J, samples))
    seg = jax.jit(lambda s, r, v: maps.sample_known(s, r, v, cfg))
    whole = jax.jit(lambda s, r, v: _whole_map(s, r, v, cfg))
    got, want = seg(store_, rows, u), whole(store_, rows, u)
    same = bool(np.array_equal(np.asarray(got[0]), np.asarray(want[0]))
                and np.array_equal(np.asarray(got[1]), np.asarray(want[1])))
    t_seg = _best(seg, (store_, rows, u), repeats)
    t_whole = _best(whole, (store_, rows, u), repeats)
    return {"store": store, "map": list(shape), "particles": J, "density": density,
            "samples": samples, "known_cells": int(np.sum(k > 0)), "same_cells": same,
            "segments_us_per_particle": 1e6 * t_seg / J,
            "whole_map_us_per_particle": 1e6 * t_whole / J, "ratio": t_whole / t_seg}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--map", type=int, nargs=2, default=[1984, 2240], metavar=("H", "W"),
                    help="map shape in cells (multiples of 8)")
    ap.add_argument("--particles", type=int, default=100)
    ap.add_argument("--density", type=float, nargs="+", default=[0.05, 0.3],
                    help="share of the map's cells known")
    ap.add_argument("--samples", type=int, default=1024, help="[filter] unknown_samples")
    ap.add_argument("--stores", nargs="+", default=["dense", "shared"])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", help="write the rows here")
    args = ap.parse_args(argv)
    for key, value in environment().items():
        print(f"# {key}: {value}")
    rows = []
    for store in args.stores:
        for density in args.density:
            r = measure(tuple(args.map), args.particles, density, args.samples, store,
                        args.repeats)
            rows.append(r)
            print(f"{store:>6} map {r['map'][0]}x{r['map'][1]} J={r['particles']} known "
                  f"{density:.0%}: segments {r['segments_us_per_particle']:.0f} us, whole map "
                  f"{r['whole_map_us_per_particle']:.0f} us per particle ({r['ratio']:.1f}x); "
                  f"same cells: {r['same_cells']}", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"environment": environment(), "rows": rows}, f, indent=1)
    return 0 if all(r["same_cells"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
