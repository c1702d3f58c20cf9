"""Search strategies beyond one fixed design, over any batched evaluator.

An evaluator maps parameter values [P, d] to objectives [P] (lower is better) in one batched
call (``evaluation.evaluate``: vmapped / sharded over sets). Each strategy records a ``Trace``:
after every evaluator call, the wall time since it started and its incumbent (best set so far
by the evaluator's own scores), so a benchmark can re-score the incumbents on fresh keys and
read off the time to reach a target.

* ``design_trace``: a fixed design (Sobol, Halton) in batches, in design order;
* ``successive_halving``: every set scored on a prefix of the course, the best fraction then on
  the full course (Jamieson & Talwalkar 2016, one rung);
* ``tpe_search``: Optuna's tree-structured Parzen estimator via ask/tell, asking a batch of sets
  per evaluator call (``pip install gslam-jax[tpe]``).
"""

from __future__ import annotations

import math
import time
from typing import Callable, NamedTuple

import numpy as np

from gslam_jax.tuning.designs import design_points
from gslam_jax.tuning.space import SearchSpace

__all__ = ["Evaluator", "Trace", "design_trace", "successive_halving", "tpe_search"]

Evaluator = Callable[[np.ndarray], np.ndarray]


class Trace(NamedTuple):
    """Incumbents after each evaluator call (lists of equal length)."""

    seconds: list[float]        # wall time since the strategy started
    incumbents: list[np.ndarray]  # [d] best set so far (by the strategy's own scores)
    scores: list[float]         # its score as the strategy saw it
    evaluated: list[int]        # sets evaluated so far (prefix runs counted as sets)


class _Recorder:
    def __init__(self) -> None:
        self.t0 = time.perf_counter()
        self.trace = Trace([], [], [], [])
        self.best: tuple[float, np.ndarray] | None = None
        self.count = 0

    def add(self, values: np.ndarray, scores: np.ndarray, incumbent_pool: bool = True) -> None:
        self.count += len(values)
        if incumbent_pool:
            ok = np.isfinite(scores)
            if ok.any():
                i = int(np.argmin(np.where(ok, scores, np.inf)))
                if self.best is None or scores[i] < self.best[0]:
                    self.best = (float(scores[i]), np.array(values[i]))
        if self.best is not None:
            t = self.trace
            t.seconds.append(time.perf_counter() - self.t0)
            t.incumbents.append(self.best[1])
            t.scores.append(self.best[0])
            t.evaluated.append(self.count)


def design_trace(evaluate: Evaluator, space: SearchSpace, design: str, n: int, batch: int,
                 seed: int = 0) -> Trace:
    """``n`` points of ``design`` evaluated ``batch`` at a time, in design order."""
    values = design_points(space, design, n, seed)
    rec = _Recorder()
    for i in range(0, n, batch):
        rec.add(values[i:i + batch], evaluate(values[i:i + batch]))
    return rec.trace


def successive_halving(evaluate_prefix: Evaluator, evaluate_full: Evaluator,
                       space: SearchSpace, n: int, keep: float = 1 / 3, design: str = "sobol",
                       seed: int = 0) -> Trace:
    """Score ``n`` design points on a prefix of the course (``evaluate_prefix``), keep the best
    ``ceil(keep n)`` and score those on the full course; the incumbent is the full course's
    best (prefix scores are not comparable with full ones, so the trace starts after the
    second rung)."""
    if not 0 < keep <= 1:
        raise ValueError(f"keep must be in (0, 1], got {keep}")
    values = design_points(space, design, n, seed)
    rec = _Recorder()
    prefix = evaluate_prefix(values)
    rec.add(values, prefix, incumbent_pool=False)
    order = np.argsort(np.where(np.isfinite(prefix), prefix, np.inf), kind="stable")
    top = values[order[:math.ceil(keep * n)]]
    rec.add(top, evaluate_full(top))
    return rec.trace


def tpe_search(evaluate: Evaluator, space: SearchSpace, n: int, batch: int, seed: int = 0,
               startup: int | None = None) -> Trace:
    """Optuna TPE (multivariate) via ask/tell: ``batch`` sets asked per evaluator call until
    ``n`` sets. ``startup``: random sets before the model is used (default one batch)."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    sampler = optuna.samplers.TPESampler(seed=seed, multivariate=True,
                                         n_startup_trials=batch if startup is None else startup,
                                         constant_liar=True)
    study = optuna.create_study(direction="minimize", sampler=sampler)
    dists = {nm: optuna.distributions.FloatDistribution(lo, hi, log=lg)
             for nm, lo, hi, lg in zip(space.names, space.lo, space.hi, space.log)}
    rec = _Recorder()
    for _ in range(0, n, batch):
        trials = [study.ask(dists) for _ in range(batch)]
        values = np.array([[t.params[nm] for nm in space.names] for t in trials])
        scores = evaluate(values)
        for t, f in zip(trials, scores):
            if np.isfinite(f):
                study.tell(t, float(f))
            else:
                study.tell(t, state=optuna.trial.TrialState.FAIL)
        rec.add(values, scores)
    return rec.trace
