"""Throughput of the batched search: P parameter sets x J particles in one jitted, vmapped and
sharded call vs looping over the P sets one by one with ``run_filter`` (same run, same key).

    XLA_FLAGS=--xla_force_host_platform_device_count=2 python -m experiments.bench_search

Both sides are timed after compilation; the ratio is printed with the machine and versions.
The two sides' objectives are compared set by set (the search's rows, sorted best first, matched
to the design's rows by their parameter values).
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from experiments.common import report  # noqa: E402
from gslam_jax import rbpf  # noqa: E402
from gslam_jax.config import Config, FilterSection, MapSection  # noqa: E402
from gslam_jax.datasets.sim import simulate_run  # noqa: E402
from gslam_jax.driver import observations, sizing  # noqa: E402
from gslam_jax.driver.machine import environment  # noqa: E402
from gslam_jax.tuning import designs as D  # noqa: E402
from gslam_jax.tuning import evaluation as E  # noqa: E402
from gslam_jax.tuning import search as S  # noqa: E402
from gslam_jax.tuning import space as SP  # noqa: E402
from gslam_jax.vo.localmap import LocalMapParams  # noqa: E402


def objective_in_design_order(values: np.ndarray, result: S.SearchResult) -> np.ndarray:
    """The search's objectives [P] in the order of the design ``values`` [P, d]: each design row
    takes the objective of the result row with the same parameter values (the search returns
    the design's own values, reordered best first)."""
    values = np.asarray(values, np.float64)
    if result.values.shape != values.shape:
        raise ValueError(f"result has {result.values.shape} values, the design {values.shape}")
    row_of = {tuple(v): i for i, v in enumerate(result.values)}
    missing = [tuple(v) for v in values if tuple(v) not in row_of]
    if missing:
        raise ValueError(f"{len(missing)} design rows are not in the result, e.g. {missing[0]}")
    return np.asarray(result.objective)[[row_of[tuple(v)] for v in values]]


def max_difference(values: np.ndarray, loop: list[float], result: S.SearchResult) -> float:
    """Largest |loop[i] - search objective of design row i| over the sets."""
    return float(np.max(np.abs(np.asarray(loop) - objective_in_design_order(values, result))))


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", type=int, default=64)
    ap.add_argument("--particles", type=int, default=100)
    ap.add_argument("--course", default="mars-yard-a")
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--cells", type=int, default=32, help="local map side (cells)")
    ap.add_argument("--batch", type=int, default=None, help="sets per chunk (default: all)")
    ap.add_argument("--repeats", type=int, default=3,
                    help="alternate batched and loop timings this many times; report the best")
    ap.add_argument("--out", default=None, help="write the figures as JSON here")
    args = ap.parse_args(argv)

    lm = LocalMapParams(resolution=0.16, max_range=2.5, travel=1.0, cells=args.cells)
    run, _ = simulate_run(args.course, 0, lm, max_frames=args.frames)
    config = Config(filter=FilterSection(particles=args.particles, unknown_cells="ignore"),
                    map=MapSection(margin=2.0))
    cfg = sizing.filter_config(config, run)
    space = SP.parse_space({"alpha_d": {"range": [0.005, 0.1], "log": True},
                           "alpha_theta_d": {"range": [0.001, 0.03], "log": True}})
    values = D.design_points(space, "sobol", args.sets)
    key = jax.random.key(0)

    # Batched: one call (compile first with the same shapes).
    S.search(run, config, space, values=values, objective="rms", key=key, batch=args.batch)

    def time_batched():
        t0 = time.perf_counter()
        res = S.search(run, config, space, values=values, objective="rms", key=key,
                       batch=args.batch)
        return time.perf_counter() - t0, res

    # Loop: the filter once per set (compiled once; parameters are traced arguments).
    base = sizing.filter_params(config)
    obs = observations.map_observations(run, config)
    controls = jnp.asarray(run.controls, jnp.float32)
    idx = jnp.asarray(run.obs_index, jnp.int32)
    start = jnp.asarray(run.start_pose(), jnp.float32)
    ref = jnp.asarray(run.ground_truth, jnp.float32)
    mask = jnp.ones(run.num_frames, bool)

    @jax.jit
    def one(v):
        p = SP.params_from_values(v, space.names, base)
        out = rbpf.run_filter(key, p, controls, idx, obs, cfg, start)
        return E.objective_value(out, "rms", ref, mask)

    one(jnp.asarray(values[0], jnp.float32)).block_until_ready()

    def time_loop():
        t0 = time.perf_counter()
        loop = [float(one(jnp.asarray(v, jnp.float32))) for v in values]
        return time.perf_counter() - t0, loop

    # Alternate the two, so that load from other processes hits both alike; keep the best.
    batched_times, loop_times = [], []
    for _ in range(args.repeats):
        t, res = time_batched()
        batched_times.append(t)
        t, loop = time_loop()
        loop_times.append(t)
    batched, looped = min(batched_times), min(loop_times)
    agree = max_difference(values, loop, res)  # set by set, in design order

    figures = {"sets": args.sets, "particles": args.particles, "frames": run.num_frames,
               "local_maps": run.num_local_maps, "map_shape": list(cfg.map_shape),
               "devices": len(jax.devices()), "batched_s": round(batched, 3),
               "loop_s": round(looped, 3),
               "batched_s_all": [round(t, 3) for t in batched_times],
               "loop_s_all": [round(t, 3) for t in loop_times],
               "speedup": round(looped / batched, 2),
               "max_objective_difference_m": agree, "environment": environment()}
    return report(figures, args.out)


if __name__ == "__main__":
    main()
