"""The motion noise fitted without ground truth: the [motion] alphas (eqs. 2-3) scaled
together by the factor that maximises the filter's log evidence (type-II maximum likelihood).

The filter's log evidence is the sum over updates of log sum_j w_j lambda_j (``StepInfo.
log_lik``, the log mean weight increment). With the paper's fixed beta (eqs. 29-31) that is a
Monte Carlo estimate of the log marginal likelihood of the log under the beta-tempered model,
and so comparable across motion noise: a prior too narrow puts no particle where the maps
agree, one too wide spreads the particles thin over poses that do not. With adaptive
tempering it is not (the exponent changes the target with the noise: a wider prior is
tempered flatter and scores lower whatever the data say), so the evidence is always taken with
``tempering = "fixed"`` and the fitted alphas are then used with the config's own tempering.

One factor scales every alpha, so their ratios stay the config's: the fit answers "how wide"
in one dimension (a ladder, not a grid over three alphas). The factors form a ladder
(``DEFAULT_FACTORS``: powers of 2 from 1/64 to 16), each run with the same PRNG keys (common
random numbers), averaged over ``seeds`` (``DEFAULT_SEEDS``); every run of a ladder is one
compiled batch (``tuning.evaluation.evaluate``).

It is meant for the simulator's point sensor, whose likelihood is exact. On stereo the
fixed-beta likelihood is overconfident and the evidence need not point at the noise the filter
does best with. Measurements: docs/notebook/results.md, "The noise fitted to the filter's
evidence", and docs/notebook/real-data.md, "The noise fitted to the filter's evidence".
"""

from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple, Sequence

import jax
import numpy as np

from gslam_jax.config import Config
from gslam_jax.driver import device_arrays, sizing
from gslam_jax.run import Run
from gslam_jax.tuning.evaluation import auto_batch, default_inner, evaluate
from gslam_jax.tuning.space import ALPHA_NAMES, SearchError

__all__ = ["DEFAULT_FACTORS", "DEFAULT_SEEDS", "MIN_GAIN", "EvidenceFit", "fit_noise_scale"]

DEFAULT_FACTORS = tuple(2.0 ** k for k in range(-6, 5))
# filter seeds averaged: one seed's ladder can peak far from where several seeds' do
# (docs/notebook/results.md, "The noise fitted to the filter's evidence")
DEFAULT_SEEDS = (0, 1, 2)
# The given alphas (factor 1, when on the ladder) are kept unless another factor's log evidence
# is higher by more than this: a Bayes factor of e^2 (about 7), "positive" evidence on Kass and
# Raftery's (1995) scale. Where the log does not constrain the noise (Arroyo A's first 600
# frames: the ladder within 1-6 nats; a log without local maps: exactly flat) the argmax alone
# would land anywhere, the ladder's edges included.
MIN_GAIN = 2.0


class EvidenceFit(NamedTuple):
    """The evidence ladder and its best rung."""

    factors: np.ndarray       # [F] the factors tried, ascending
    log_evidence: np.ndarray  # [F] the mean log evidence over the seeds (NaN: a failed run)
    factor: float             # the chosen factor (``fit_noise_scale``)
    alphas: dict[str, float]  # the config's [motion] alphas times ``factor``
    on_edge: bool             # the chosen factor is the ladder's smallest or largest
    kept: bool                # factor 1 kept over the argmax (no more than MIN_GAIN above it)

    def config(self, config: Config) -> Config:
        """``config`` with its [motion] alphas replaced by the fitted ones."""
        return dataclasses.replace(config, motion=dataclasses.replace(config.motion,
                                                                      **self.alphas))


def fit_noise_scale(run: Run, config: Config, factors: Sequence[float] = DEFAULT_FACTORS,
                    seeds: Sequence[int] = DEFAULT_SEEDS,
                    progress: Callable[[int, int], None] | None = None) -> EvidenceFit:
    """The factor of ``factors`` whose alphas (``config``'s times the factor) give ``run`` the
    highest log evidence under fixed tempering, averaged over the filter ``seeds``; 1 (the
    given alphas) when it is on the ladder and no factor beats it by more than ``MIN_GAIN``.

    A SearchError for a factor that is not positive and finite, no factors or no seeds, all
    alphas zero (nothing to scale), or a ladder whose every run failed (NaN evidence)."""
    factors = np.sort(np.asarray(list(factors), np.float64))
    if factors.size == 0 or not np.all(np.isfinite(factors) & (factors > 0)):
        raise SearchError(f"factors must be positive and finite, got {factors.tolist()}")
    if len(seeds) == 0:
        raise SearchError("seeds: at least one filter seed is needed")
    base = np.array([getattr(config.motion, n) for n in ALPHA_NAMES], np.float64)
    if not np.any(base > 0):
        raise SearchError("[motion] every alpha is 0: there is no noise to scale")
    fixed = dataclasses.replace(config, filter=dataclasses.replace(config.filter,
                                                                   tempering="fixed"))
    inputs, cfg = device_arrays.run_arrays(run, fixed)
    params = sizing.filter_params(fixed, run)
    values = factors[:, None] * base[None, :]
    devices = jax.devices()
    batch = auto_batch(cfg, run.num_frames, num_devices=len(devices),
                       inner=default_inner(devices))  # the search's memory bound
    total = np.zeros(factors.size)
    for i, seed in enumerate(seeds):
        total += evaluate(values, jax.random.key(seed), inputs, params, ALPHA_NAMES,
                          cfg, "loglik", batch=min(batch, factors.size))
        if progress is not None:
            progress(i + 1, len(seeds))
    log_ev = total / len(seeds)
    if not np.any(np.isfinite(log_ev)):
        raise SearchError(f"the log evidence was NaN for every factor {factors.tolist()}: "
                          "particles observed beyond the map's edge (widen [map] margin) or, "
                          "with [map] store = \"shared\", the tile pool ran out (raise [map] "
                          "pool_tiles)")
    finite = np.where(np.isfinite(log_ev), log_ev, -np.inf)
    best = int(np.argmax(finite))
    given = np.flatnonzero(factors == 1.0)
    kept = bool(given.size) and best != given[0] and finite[best] - finite[given[0]] <= MIN_GAIN
    if kept:
        best = int(given[0])  # no factor is clearly better than the given noise
    alphas = {n: float(v) for n, v in zip(ALPHA_NAMES, values[best])}
    return EvidenceFit(factors, log_ev, float(factors[best]), alphas,
                       best in (0, factors.size - 1), kept)
