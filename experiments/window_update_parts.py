"""Where the window store's update spends its time on KITTI 00's loop (issue 67): one compiled
``scan_frames`` over a stretch of the loop from a mid-loop state, with parts of the update
switched off, each variant compiled once and then run in turns (so a machine whose load
drifts weighs on every variant alike), best of the rounds.

    python -m experiments.window_update_parts --particles 500 --start 750 --stop 1450
    python -m experiments.window_update_parts --variants full no-moves no-refill no-zeroing

Variants (the switched-off parts are replaced before tracing; the numbers they compute are
not the filter's, only their time is of interest):

* ``full``: the update as it is;
* ``no-moves``: ``windowstore.finish_update`` only records the update (no window moves);
* ``no-refill``: windows move and their entering cells are zeroed, but not refilled;
* ``no-zeroing``: windows move and are refilled, but entering cells are not zeroed first;
* ``full-search``: every refill turns the groups' boxes of all U past local maps (the refill
  before its heading-free pre-test, ``windowstore._near``);
* ``no-updates``: no frame has a local map (the motion draws and the per-frame outputs);
* ``no-range-noise``: eq. 26 without the range profile's measurement variance.

The loop is ``experiments.window_store``'s (its ``--cache``), the window store with the whole
loop's history (``[map] pool_tiles`` = 972) unless ``--prefix-history``. Prints the machine
and versions, then one JSON line per variant: us per particle per update and every round's
seconds.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Callable

VARIANTS = ("full", "no-moves", "no-refill", "no-zeroing", "full-search", "no-updates",
            "no-range-noise")
LOOP_MAPS = 972  # local maps of KITTI 00's loop (experiments.window_store)


def _patches(variant: str) -> dict[str, Callable]:
    """The ``windowstore`` functions ``variant`` replaces."""
    import jax.numpy as jnp

    from gslam_jax.rbpf import windowstore as ws

    if variant == "no-moves":
        return {"finish_update": lambda store, pose, obs, cfg, replays=128:
                ws._record(store, pose, obs, cfg)}
    if variant == "no-refill":
        return {"_refill": lambda store, k, S, ids, mv, cfg, R: (k, S, jnp.bool_(False))}
    if variant == "no-zeroing":
        return {"_zero_entered": lambda x, ids, mv, width: x}
    if variant == "full-search":
        return {"_near": lambda path, recorded, mv, C, cfg: recorded}
    return {}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--particles", type=int, default=500)
    ap.add_argument("--start", type=int, default=750, help="frame the timed stretch starts at")
    ap.add_argument("--stop", type=int, default=1450, help="frame it ends before")
    ap.add_argument("--variants", nargs="+", default=["full", "no-moves"], choices=VARIANTS)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--prefix-history", action="store_true",
                    help="the history sized to the frames run, not the whole loop's")
    ap.add_argument("--cache", type=Path, default=Path("results/window_store"))
    args = ap.parse_args(argv)

    import jax
    import jax.numpy as jnp
    import numpy as np

    from experiments.window_store import _config, cached_run
    from gslam_jax import rbpf
    from gslam_jax.config import apply_overrides
    from gslam_jax.driver.machine import environment
    from gslam_jax.driver.map_axes import filtered_run
    from gslam_jax.driver.observations import map_observations
    from gslam_jax.driver.sizing import filter_config, filter_params
    from gslam_jax.gridmap.relocalise import run_prefix
    from gslam_jax.rbpf import windowstore as ws

    env = environment()
    print(f"# {env['date']} | {env.get('processor', '')} | {env['cpus']} cpus | "
          f"jax {env['jax']} | numpy {np.__version__}", flush=True)
    J, F0, F1 = args.particles, args.start, args.stop
    run, margin = cached_run(args.cache)
    run = run_prefix(run, F1)
    history = [] if args.prefix_history else [f"map.pool_tiles={LOOP_MAPS}"]
    config = apply_overrides(_config("window", J), [f"map.margin={margin:g}"] + history)
    _, _, run = filtered_run(run, config, None)
    cfg = filter_config(config, run, None)
    params = filter_params(config, run)
    obs = map_observations(run, config)
    headings = jnp.asarray(run.lattice_heading_array())
    keys = rbpf.frame_keys(jax.random.key(0), run.num_frames)
    controls = jnp.asarray(np.asarray(run.controls, np.float32))
    index = np.asarray(run.obs_index, np.int32)
    state = rbpf.init(cfg, jnp.asarray(run.start_pose(), jnp.float32))
    state, _ = rbpf.scan_frames(state, keys[:F0], controls[:F0], jnp.asarray(index[:F0]), obs,
                                params, cfg, headings)
    state = jax.block_until_ready(state)
    updates = int(np.sum(index[F0:F1] >= 0))
    print(f"# J = {J}, frames {F0}-{F1} ({updates} updates), window {ws.side(cfg)} cells, "
          f"M = {cfg.max_observed}, history {ws.history(cfg)} local maps", flush=True)

    compiled = {}
    for variant in args.variants:
        patches = _patches(variant)
        saved = {name: getattr(ws, name) for name in patches}
        p = params._replace(range_noise=None) if variant == "no-range-noise" else params
        o = jnp.asarray(-np.ones(F1 - F0, np.int32) if variant == "no-updates"
                        else index[F0:F1])
        try:
            for name, fn in patches.items():
                setattr(ws, name, fn)
            jax.clear_caches()
            copy = jax.tree.map(jnp.copy, state)
            compiled[variant] = (rbpf.scan_frames.lower(copy, keys[F0:F1], controls[F0:F1], o,
                                                        obs, p, cfg, headings).compile(), p, o)
        finally:
            for name, fn in saved.items():
                setattr(ws, name, fn)
    seconds: dict[str, list[float]] = {v: [] for v in args.variants}
    for _ in range(args.rounds):
        for variant, (fn, p, o) in compiled.items():
            copy = jax.tree.map(jnp.copy, state)
            t0 = time.perf_counter()
            jax.block_until_ready(fn(copy, keys[F0:F1], controls[F0:F1], o, obs, p, headings))
            seconds[variant].append(time.perf_counter() - t0)
    for variant, times in seconds.items():
        print(json.dumps({"variant": variant, "us_per_particle_update":
                          round(1e6 * min(times) / max(updates, 1) / J, 1),
                          "seconds": [round(t, 3) for t in times]}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
