"""The batched search on a Dask cluster: each worker evaluates vmapped, device-sharded chunks of
parameter sets on its own devices (``evaluation.evaluate``); the client designs, gathers and
ranks.

Why Dask (``pip install gslam-jax[distributed]``): the search is a map of independent chunks
over workers, which is what ``Client.submit`` does; ``distributed`` is pure Python (a few MB,
installs in seconds beside NumPy), a 2-worker ``LocalCluster`` starts in seconds (so its test
runs in CI), and the same code reaches many machines through ``dask scheduler`` /
``dask worker`` or dask-jobqueue on a SLURM/PBS cluster, the usual setting of the researchers
who run this. Ray would serve as well but weighs far more to install and start for a plain
map.

Results equal ``search.search`` for the same config, key and ``batch``: the chunks are the
same (``evaluation.chunk_size`` over the client's count of devices per worker), every set uses the
same PRNG key (common random numbers), and a set's objective does not depend on the chunk it
runs in.
"""

from __future__ import annotations

import math
import time
from typing import Any, Callable, Sequence

import jax
import numpy as np

from gslam_jax.config import Config
from gslam_jax.driver import device_arrays, sizing
from gslam_jax.run import Run
from gslam_jax.tuning.evaluation import chunk_size, evaluate
from gslam_jax.tuning.search import SearchResult, design_values, finish
from gslam_jax.tuning.space import SearchError, SearchSpace

__all__ = ["evaluate_chunk", "distributed_evaluate", "distributed_search"]


def evaluate_chunk(values: np.ndarray, run: Run, config: Config, names: tuple[str, ...],
                   key_data: np.ndarray, objective: str, path: str) -> np.ndarray:
    """On a worker: the objectives of one chunk [B, d], sharded over that worker's JAX devices
    in one call (``evaluation.evaluate`` with ``batch`` = B)."""
    inputs, cfg = device_arrays.run_arrays(run, config, names)
    key = jax.random.wrap_key_data(np.asarray(key_data))
    return evaluate(values, key, inputs, sizing.filter_params(config, run), names, cfg, objective,
                    path, batch=len(values))


def distributed_evaluate(client: Any, values: np.ndarray, run: Run, config: Config,
                         names: Sequence[str], key: jax.Array, objective: str,
                         path: str = "mean", batch: int | None = None,
                         devices_per_worker: int | None = None,
                         progress: Callable[[int, int], None] | None = None) -> np.ndarray:
    """Objective of every row of ``values`` [P, d], chunks spread over ``client``'s workers
    (a ``distributed.Client``). batch: sets per chunk (default: the sets split evenly over the
    workers), rounded like the single-process search (``evaluation.chunk_size`` with
    ``devices_per_worker``, default this process's device count)."""
    values = np.asarray(values, np.float64)
    P = len(values)
    workers = max(1, len(client.scheduler_info()["workers"]))
    nd = devices_per_worker or len(jax.devices())
    batch = chunk_size(P, batch or math.ceil(P / workers), nd)
    run_f, config_f = client.scatter([run, config], broadcast=True)
    key_data = np.asarray(jax.random.key_data(key))
    futures = {client.submit(evaluate_chunk, values[i:i + batch], run_f, config_f, tuple(names),
                             key_data, objective, path, pure=False): i
               for i in range(0, P, batch)}
    from distributed import as_completed

    out = np.empty(P, np.float64)
    done = 0
    for fut in as_completed(futures):
        i = futures[fut]
        res = fut.result()
        out[i:i + len(res)] = res
        done += len(res)
        if progress is not None:
            progress(done, P)
    return out


def distributed_search(client: Any, run: Run, config: Config, space: SearchSpace,
                       design: str = "halton", n: int = 64, objective: str = "rms", *,
                       path: str = "mean", key: jax.Array | None = None, seed: int = 0,
                       batch: int | None = None, values: np.ndarray | None = None,
                       devices_per_worker: int | None = None,
                       progress: Callable[[int, int], None] | None = None) -> SearchResult:
    """``search.search`` on a Dask cluster (same arguments, same checks, same ranking)."""
    values = design_values(run, space, design, n, objective, path, seed, values)
    if objective == "rms":
        device_arrays.require_ground_truth(device_arrays.ground_truth_mask(run), "rms", SearchError)
    key = jax.random.key(config.filter.seed) if key is None else key
    t0 = time.perf_counter()
    first: list[float] = []

    def timed(done: int, total: int) -> None:
        if not first:
            first.append(time.perf_counter() - t0)  # the first chunk back, compilation included
        if progress is not None:
            progress(done, total)

    f = distributed_evaluate(client, values, run, config, space.names, key, objective, path,
                             batch, devices_per_worker, timed)
    return finish(space, values, f, objective, time.perf_counter() - t0, first[0])
