"""The batched parameter search: a design over a search space, evaluated on a Run, ranked.

The paper tuned alpha_d, alpha_theta_d, alpha_theta (eqs. 2-3) and the tempering constants
beta_prev, beta_new (eqs. 29-31) by hand per environment (section 7.3). ``search`` evaluates
the points of a design (``designs``) over named ranges of the searchable settings (``space``)
in batched, device-sharded chunks (``evaluation``) and ranks them best first.
"""

from __future__ import annotations

import csv
import json
import math
import time
import warnings
from pathlib import Path
from typing import Any, Callable, NamedTuple, Sequence

import jax
import numpy as np
from jax import Array

from gslam_jax.config import Config
from gslam_jax.driver import device_arrays, sizing
from gslam_jax.run import Run
from gslam_jax.tuning.designs import design_points
from gslam_jax.tuning.evaluation import OBJECTIVES, PATHS, auto_batch, default_inner, evaluate
from gslam_jax.tuning.space import SearchError, SearchSpace

__all__ = ["SearchResult", "rank", "design_values", "search", "finish"]

PROGRESS_CHUNKS = 8  # chunks of a search whose sets run one after another (progress reports)


class SearchResult(NamedTuple):
    """Evaluated design, rows sorted best first (NaN rows last, flagged).

    total_seconds: wall time of every chunk, compilation included. first_chunk_seconds: the
    first chunk alone (compilation plus its compute), a part of ``total_seconds``, not to be
    added to it.
    """

    names: tuple[str, ...]
    values: np.ndarray     # [P, d] parameter values, best first
    objective: np.ndarray  # [P] objective values, best first (NaN last)
    objective_name: str
    maximize: bool
    total_seconds: float
    first_chunk_seconds: float

    @property
    def num_nan(self) -> int:
        return int(np.sum(~np.isfinite(self.objective)))

    def best(self) -> dict[str, float]:
        """The best parameter set; an error if every objective was NaN."""
        if not np.isfinite(self.objective[0]):
            raise SearchError(f"objective '{self.objective_name}' was NaN or infinite for all "
                              f"{len(self.objective)} parameter sets; nothing to rank")
        return dict(zip(self.names, map(float, self.values[0])))

    def rows(self) -> list[dict[str, Any]]:
        out = []
        for rank, (v, f) in enumerate(zip(self.values, self.objective), 1):
            ok = bool(np.isfinite(f))
            row = {"rank": rank if ok else None}
            row.update({n: float(x) for n, x in zip(self.names, v)})
            row[self.objective_name] = float(f) if ok else None
            row["status"] = "ok" if ok else "nan"
            out.append(row)
        return out

    def to_csv(self, path: str | Path) -> None:
        rows = self.rows()
        with open(path, "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
            writer.writeheader()
            for r in rows:
                writer.writerow({k: ("nan" if v is None and k == self.objective_name else
                                     ("" if v is None else v)) for k, v in r.items()})

    def to_json(self, path: str | Path) -> None:
        doc = {"objective": self.objective_name, "maximize": self.maximize,
               "total_seconds": self.total_seconds,
               "first_chunk_seconds": self.first_chunk_seconds,
               "num_nan": self.num_nan, "results": self.rows()}
        Path(path).write_text(json.dumps(doc, indent=2))


def rank(values: np.ndarray, objective: np.ndarray, maximize: bool
         ) -> tuple[np.ndarray, np.ndarray]:
    """Sort best first; NaN / infinite objectives go last whatever their sign."""
    f = np.asarray(objective, np.float64)
    finite = np.isfinite(f)
    key = np.where(finite, -f if maximize else f, 0.0)
    order = np.lexsort((key, ~finite))  # finite first, then by objective (stable)
    return values[order], f[order]


def design_values(run: Run, space: SearchSpace, design: str, n: int, objective: str,
                  path: str, seed: int, values: np.ndarray | None) -> np.ndarray:
    """Check a search request (objective, path, ground truth for "rms") and return its
    parameter values [P, d]: ``values`` if given, else the design's points."""
    if objective not in OBJECTIVES:
        raise SearchError(f"objective '{objective}' unknown; choose one of "
                          f"{', '.join(OBJECTIVES)}")
    if path not in PATHS:
        raise SearchError(f"path '{path}' unknown; choose one of {', '.join(PATHS)}")
    if objective == "rms" and run.ground_truth is None:
        raise SearchError("objective 'rms' needs the run's ground_truth, which is missing; "
                          "use objective 'loglik'")
    if values is None:
        values = design_points(space, design, n, seed)
    values = np.asarray(values, np.float64)
    if values.ndim != 2 or values.shape[1] != space.dim:
        raise SearchError(f"values must be [P, {space.dim}], got {values.shape}")
    return values


def search(run: Run, config: Config, space: SearchSpace, design: str = "halton", n: int = 64,
           objective: str = "rms", *, path: str = "mean", key: Array | None = None,
           crn: bool = True, seed: int = 0, batch: int | None = None,
           devices: Sequence[jax.Device] | None = None,
           progress: Callable[[int, int], None] | None = None,
           values: np.ndarray | None = None, inner: int | None = None) -> SearchResult:
    """Evaluate ``n`` parameter sets of ``design`` over ``space`` on ``run``; best first.

    config: everything not searched (particles, resampler, map, and the base values of the
    parameters not in ``space``). objective: "rms" (needs ground truth; m, lower is better) or
    "loglik" (higher is better). path: "mean" (weighted-mean pose per frame), "best" (the
    final best particle's path) or "smoothed" (``rbpf.smoothed_mean_path``) for "rms". crn:
    the same PRNG key for every set (common random numbers); only True is supported (False is
    a SearchError: repeat the search with other keys instead). batch: sets per chunk (default
    ``auto_batch``). values: an explicit [P, d] design (overrides design and n). inner: sets
    vmapped together per device (see ``evaluate``). The result's ``total_seconds`` include
    compilation; ``first_chunk_seconds`` are the part spent on the first chunk (compilation
    and its compute).
    """
    values = design_values(run, space, design, n, objective, path, seed, values)
    # evaluate() checks "rms"'s truth
    inputs, cfg = device_arrays.run_arrays(run, config, space.names, SearchError)
    base = sizing.filter_params(config, run)
    key = jax.random.key(config.filter.seed) if key is None else key
    if not crn:
        raise SearchError("crn=False is not supported by the batched search: every set uses "
                          "the same key (common random numbers); repeat the search with "
                          "different keys instead")
    devices = list(devices or jax.devices())
    inner = default_inner(devices) if inner is None else inner
    if batch is None:
        batch = auto_batch(cfg, run.num_frames, num_devices=len(devices), inner=inner)
        if inner is not None:  # sets run one after another: chunks for progress reports
            batch = min(batch, math.ceil(len(values) / PROGRESS_CHUNKS))
    t0 = time.perf_counter()
    first_chunk_s = 0.0
    first = [True]

    def timed_progress(done: int, total: int) -> None:
        nonlocal first_chunk_s
        if first[0]:
            first_chunk_s = time.perf_counter() - t0  # compilation and the first chunk
            first[0] = False
        if progress is not None:
            progress(done, total)

    f = evaluate(values, key, inputs, base, tuple(space.names), cfg, objective, path,
                 batch=batch, devices=devices, progress=timed_progress, inner=inner)
    return finish(space, values, f, objective, time.perf_counter() - t0, first_chunk_s)


POOL_NOTE = ('with [map] store = "shared", a run whose tile pool ran out scores NaN too: raise '
             '[map] pool_tiles; for loglik, so does a run whose particles observed beyond the '
             'map\'s edge: widen [map] margin')


def finish(space: SearchSpace, values: np.ndarray, f: np.ndarray, objective: str,
           total_s: float, first_chunk_s: float) -> SearchResult:
    """Rank evaluated sets into a SearchResult: a SearchError when every objective is NaN, a
    RuntimeWarning naming one when some are (shared by ``search`` and
    ``distributed.distributed_search``)."""
    bad = ~np.isfinite(f)
    if bad.all():
        raise SearchError(f"objective '{objective}' is NaN or infinite for every one of the "
                          f"{len(f)} parameter sets (first: "
                          f"{dict(zip(space.names, values[0].round(6)))}); check the run and "
                          f"the ranges ({POOL_NOTE})")
    if bad.any():
        first_bad = dict(zip(space.names, values[np.argmax(bad)].round(6)))
        warnings.warn(f"objective '{objective}' is NaN for {int(bad.sum())} of {len(f)} "
                      f"parameter sets (e.g. {first_bad}); they are reported last, never "
                      f"ranked best ({POOL_NOTE})", RuntimeWarning)
    maximize = objective == "loglik"
    vals, obj = rank(values, f, maximize)
    return SearchResult(tuple(space.names), vals, obj, objective, maximize, total_s,
                        first_chunk_s)
