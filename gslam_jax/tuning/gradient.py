"""Gradient-based tuning of the noise parameters with optax.

The filter's map lookup is a floor of the particle pose and resampling is discrete, so plain
autodiff of ``run_filter`` gives zero or biased gradients. This module re-runs the same filter
(same draws, same numbers in the forward pass: ``rbpf.step``, the filter's own frame, with the
proposal ``sw_propose`` and the resampler ``sw_resample`` passed in) with the stop-gradient
estimator of Scibior & Wood (2021, "Differentiable particle filtering without modifying the
forward pass"):

* particle poses are sampled from the motion model (eqs. 1-3) and then stop-gradiented, so no
  gradient flows through the map lookup;
* each particle's log weight gains ``log p_theta(x_t | x_{t-1}, u_t) - stop_gradient(same)``:
  zero in value, the score of the transition density in gradient;
* the importance factor (eqs. 26, 30-31) carries the gradient in the tempering constants
  beta_prev and beta_new directly;
* resampling picks ancestors from the stop-gradiented weights and sets the new log weight to
  ``-log J + lw[a] - stop_gradient(lw[a])``, so the ancestry's gradient survives resampling.

The gradient of the log marginal likelihood estimate sum_t log sum_j w_j lambda_j then is the
Fisher-identity estimator (the expected score of the transition densities along the ancestral
paths under the smoothing distribution). The supervised objective is the expected squared
position error under the filtering weights, self-normalised, E_w ||x_t - x_t^true||^2 averaged
over frames; its gradient by the same weights is the score-function (likelihood-ratio) gradient
of the filtering expectation.

Parameters are optimised in log space (they stay positive) by an optax optimiser named by its
constructor (``optax.adam``, ``optax.sgd``, ...) whose update takes the gradient alone; those
that need more in their update (``optax.lbfgs``: value, grad, value_fn; ``optax.polyak_sgd``:
value) are rejected before the run.
"""

from __future__ import annotations

import math
import time
from typing import Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax import Array, lax

from gslam_jax import choices, rbpf
from gslam_jax.config import Config
from gslam_jax.driver import device_arrays, sizing
from gslam_jax.errors import InputError
from gslam_jax.rbpf import maps
from gslam_jax.rbpf.motion import MotionParams, motion_stds
from gslam_jax.run import Run
from gslam_jax.tuning.space import (
    FILTER_PARAM_NAMES,
    MOTION_PARAM_NAMES,
    SETTINGS,
    TUNABLE_NAMES,
    base_values,
    observations_from_values,
    params_from_values,
)

__all__ = ["TUNE_OBJECTIVES", "TuneError", "TuneInputs", "TuneResult", "transition_score",
           "sw_propose", "sw_resample", "sw_objectives", "objective_fn", "make_inputs", "tune",
           "default_names"]

TUNE_OBJECTIVES = choices.TUNE_OBJECTIVES
sg = lax.stop_gradient


class TuneError(InputError):
    """A bad tuning request; the message names the field."""


TuneInputs = device_arrays.RunArrays  # the Run's device arrays (``run_arrays``, raw observations)


class Objectives(NamedTuple):
    loglik: Array      # sum over updates of log sum_j w_j lambda_j (value as the filter's)
    sq_error: Array    # mean over frames of E_w ||x - x_true||^2 (m^2)
    map_status: Array  # [] int32 the map store's sticky error bits at the end (0: fine)


def transition_score(eps: Array, u: Array, params: MotionParams) -> Array:
    """``log p_theta(x_t | x_{t-1}, u_t) - stop_gradient(same)`` for particles moved by
    standard-normal draws ``eps`` [J, 3] (Scibior & Wood 2021): zero in value, the score of the
    transition density (eqs. 1-3) w.r.t. the alphas in gradient.

    The sampled residuals are sg(sigma) * eps; their density under sigma(theta) is
    N(sg(sigma) eps; 0, sigma^2), written from eps directly rather than recovered from the
    poses (no float32 cancellation). Along-track: sigma_d = alpha_d |d|; heading:
    sigma_theta = alpha_theta_d |d| + alpha_theta |dtheta|; cross-track: sigma_c =
    alpha_cross |d|. Zero-std components (no motion, or a zero alpha) contribute nothing.
    """
    dist, _, sigma_t = motion_stds(u, params)

    def normal(residual_scale: Array, e: Array, moves: Array) -> Array:
        """log N(sg(a) e; 0, a^2) up to its constant, 0 where a = 0 or nothing moves. Safe
        stand-ins inside where: a zero std gives neither a NaN value nor a NaN gradient."""
        on = moves & (residual_scale > 0)
        a = jnp.where(on, residual_scale, 1.0)
        return jnp.where(on, -0.5 * (sg(a) * e / a) ** 2 - jnp.log(a), 0.0)

    moved = dist > 0
    lp = (normal(params.alpha_d, eps[..., 0], moved)  # sigma_d / |d|: |d| is no parameter
          + normal(sigma_t, eps[..., 1], jnp.ones_like(moved))
          + normal(jnp.asarray(params.alpha_cross), eps[..., 2], moved))
    return lp - sg(lp)


def sw_propose(state: rbpf.FilterState, u: Array, eps: Array, params: rbpf.FilterParams
               ) -> rbpf.FilterState:
    """The Scibior-Wood proposal (an ``rbpf.Proposal``): particles moved as the filter moves
    them, stop-gradiented (no gradient through the map lookup); each log weight gains
    ``transition_score`` (zero in value)."""
    pose = sg(rbpf.predict(sg(state.pose), u, eps, jax.tree.map(sg, params)))
    return state._replace(pose=pose, log_w=state.log_w + transition_score(eps, u, params.motion))


def sw_resample(state: rbpf.FilterState, u: Array, cfg: rbpf.FilterConfig
                ) -> tuple[rbpf.FilterState, Array, Array]:
    """The Scibior-Wood resampler (an ``rbpf.Resampler``): the filter's ESS-gated resampling
    (stop-gradient choice and ancestors) with new log weights ``-log J + lw[a] - sg(lw[a])``,
    equal in value, so the ancestry's gradient survives. No gradient flows through the maps'
    copies (the map lookup carries none either)."""
    J = cfg.num_particles
    state = state._replace(maps=sg(state.maps))
    return rbpf.resample(state, u, cfg, new_log_w=lambda lwa: -math.log(J) + (lwa - sg(lwa)))


def sw_objectives(key: Array, params: rbpf.FilterParams, inputs: TuneInputs,
                  cfg: rbpf.FilterConfig) -> Objectives:
    """One filter run with Scibior-Wood stop-gradient weights (see the module docstring):
    ``rbpf.step``, the filter's own frame, with ``sw_propose`` and ``sw_resample``.

    Same draws as ``rbpf.run_filter(key, ...)``: the forward values equal the filter's.
    """
    state = rbpf.init(cfg, inputs.start)
    keys = rbpf.frame_keys(key, inputs.controls.shape[0])

    def frame(state: rbpf.FilterState, xs):
        k, u, idx, ref, m, fallback = xs
        local = jnp.maximum(idx, 0)
        state, info = rbpf.step(k, state, u, inputs.local_obs[local], params, cfg, idx >= 0,
                                propose=sw_propose, resampler=sw_resample,
                                lattice_heading=inputs.lattice_headings[local],
                                fallback=False if fallback is None else fallback)
        w = jax.nn.softmax(state.log_w)  # self-normalised: weights carry the gradient
        d2 = jnp.sum((state.pose[:, :2] - ref[:2]) ** 2, axis=-1)
        return state, (info.log_lik, jnp.where(m, w @ d2, 0.0))

    state, (ll, err) = lax.scan(frame, state, (keys, inputs.controls, inputs.obs_index,
                                               inputs.reference, inputs.mask,
                                               inputs.fallback))
    n = jnp.maximum(jnp.sum(inputs.mask), 1)
    return Objectives(jnp.sum(ll), jnp.sum(err) / n, maps.status(state.maps))


def make_inputs(run: Run, config: Config) -> tuple[TuneInputs, rbpf.FilterConfig]:
    """Device inputs and the static filter config for ``run`` (``device_arrays.run_arrays``)."""
    return device_arrays.run_arrays(run, config)


def objective_fn(log_values: Array, keys: Array, base: rbpf.FilterParams, inputs: TuneInputs,
                 names: tuple[str, ...], cfg: rbpf.FilterConfig, objective: str
                 ) -> tuple[Array, Array]:
    """Loss to minimise at log parameter values [d], averaged over independent runs ``keys``
    [K]: ``-loglik / updates`` or the mean expected squared error (m^2); and, as the auxiliary
    output, the map store's error bits over the runs (0: fine). The raw ``inputs.local_obs``
    are refined with the named observation settings, the others from ``inputs.obs``."""
    values = jnp.exp(log_values)
    params = params_from_values(values, names, base)
    inputs = inputs._replace(local_obs=observations_from_values(values, names, inputs.obs,
                                                                inputs.local_obs))
    # lax.map, not vmap: under vmap the data-dependent resampling cond would become a select
    # over every map (both branches run, the copy loop over the whole batch).
    obj = lax.map(lambda k: sw_objectives(k, params, inputs, cfg), keys)
    if objective == "loglik":
        n_upd = jnp.maximum(jnp.sum(inputs.obs_index >= 0), 1)
        return -jnp.mean(obj.loglik) / n_upd, jnp.max(obj.map_status)
    return jnp.mean(obj.sq_error), jnp.max(obj.map_status)


_value_and_grad = jax.jit(jax.value_and_grad(objective_fn, has_aux=True),
                          static_argnames=("names", "cfg", "objective"))


def _optimizer(name: str, lr: float, kwargs: dict, x: Array
               ) -> tuple[optax.GradientTransformation, optax.OptState]:
    """``getattr(optax, name)(lr, **kwargs)`` and its initial state, checked before any filter
    run: it must be a gradient transformation whose update takes (gradient, state, params)
    alone (one trial update on a zero gradient, discarded)."""
    try:
        opt = getattr(optax, name)(lr, **kwargs)
    except (TypeError, ValueError) as err:  # ValueError: optax rejecting an argument's value
        raise TuneError(f"optimizer '{name}' cannot be built as optax.{name}(learning_rate, "
                        f"**optimizer_kwargs): {type(err).__name__}: {err}") from err
    if not isinstance(opt, optax.GradientTransformation):
        raise TuneError(f"optimizer '{name}' is not an optax optimiser (optax.{name}(...) gave "
                        f"{type(opt).__name__}, not a GradientTransformation)")
    try:
        state = opt.init(x)
    except (TypeError, ValueError) as err:  # e.g. a mask that does not fit the parameters
        raise TuneError(f"optimizer '{name}' cannot be initialised on the {x.shape[0]} tuned "
                        f"parameter(s) with optimizer_kwargs {kwargs}: "
                        f"{type(err).__name__}: {err}") from err
    try:
        opt.update(jnp.zeros_like(x), state, x)
    except TypeError as err:
        raise TuneError(f"optimizer '{name}' needs extra arguments in its update ({err}); tune "
                        f"passes the gradient only: use an optimiser whose update needs nothing "
                        f"more, such as adam or sgd") from err
    except ValueError as err:
        raise TuneError(f"optimizer '{name}' fails on a trial update with optimizer_kwargs "
                        f"{kwargs}: ValueError: {err}") from err
    return opt, state


class TuneResult(NamedTuple):
    names: tuple[str, ...]
    values: dict[str, float]    # tuned parameters
    history: np.ndarray         # [steps + 1, d] parameter values (start first)
    losses: np.ndarray          # [steps] loss at the step's parameters (before its update)
    objective: str
    seconds: float


def default_names(objective: str, start: dict[str, float] | None = None) -> tuple[str, ...]:
    """The alphas for "loglik" (the tempered likelihood is not normalised in the betas), the
    filter parameters (alphas and betas) for "supervised"; less those whose ``start`` value
    is 0 (a term switched off, as alpha_cross by default: log space cannot start there) and
    ``fallback_scale`` (it matters only on a run with fallback frames: tuned when named)."""
    names = MOTION_PARAM_NAMES if objective == "loglik" else FILTER_PARAM_NAMES
    return tuple(n for n in names if not SETTINGS[n].ratio
                 and (start is None or start.get(n, 1.0) != 0.0))


def tune(run: Run, config: Config, objective: str = "loglik", optimizer: str = "adam",
         lr: float = 0.05, steps: int = 100, *, names: Sequence[str] | None = None,
         start: dict[str, float] | None = None, runs_per_step: int = 4, key: Array | None = None,
         crn: bool = False, optimizer_kwargs: dict | None = None,
         progress: Callable[[int, int], None] | None = None,
         on_step: Callable[[int, float, dict[str, float]], None] | None = None) -> TuneResult:
    """Tune ``names`` by ``optimizer`` (``getattr(optax, optimizer)(lr, **optimizer_kwargs)``,
    an optimiser whose update takes the gradient alone: those needing extra update arguments,
    e.g. ``lbfgs``, are a TuneError before any filter run).

    objective: "loglik" (maximise the log marginal likelihood estimate; alphas only) or
    "supervised" (minimise the expected squared position error against ground truth).
    start: initial values (default: the config's). runs_per_step: independent filter runs
    averaged per gradient. crn: reuse the same keys every step (common random numbers);
    otherwise step s uses keys derived from fold_in(key, s). "supervised" needs a frame with a
    finite ground-truth position (x, y; headings are not used), a TuneError otherwise (the loss
    would be 0 for every parameter value). on_step(step, loss, values) is called after every
    step with the loss at the step's parameters and the updated values. Tunable: every
    searchable setting but the integer thresholds (min_points: no gradient).
    """
    if objective not in TUNE_OBJECTIVES:
        raise TuneError(f"objective '{objective}' unknown; choose one of "
                        f"{', '.join(TUNE_OBJECTIVES)}")
    if config.filter.proposal != "motion":
        raise TuneError(f"[filter] proposal = \"{config.filter.proposal}\": gradient tuning "
                        "differentiates the motion proposal only; tune with proposal = \"motion\"")
    cur = base_values(config)
    cur.update(start or {})
    names = tuple(names) if names is not None else default_names(objective, cur)
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise TuneError(f"parameters named twice: {', '.join(repeated)}; name each once")
    for n in names:
        if n not in SETTINGS:
            raise TuneError(f"unknown parameter '{n}'; tunable: {', '.join(TUNABLE_NAMES)}")
        if SETTINGS[n].integer:
            raise TuneError(f"{n} is a threshold (the loss is flat between integers, no "
                            f"gradient); search it with gslam search instead")
    if objective == "loglik" and any(n not in MOTION_PARAM_NAMES for n in names):
        raise TuneError("objective 'loglik' tunes the motion noise only (the alphas and "
                        "fallback_scale): the tempered likelihood "
                        "(eqs. 29-31) is not normalised in beta_prev/beta_new, nor across "
                        "observation settings (they change the data); use 'supervised'")
    if objective == "supervised" and run.ground_truth is None:
        raise TuneError("objective 'supervised' needs the run's ground_truth, which is missing")
    if not hasattr(optax, optimizer) or not callable(getattr(optax, optimizer)):
        raise TuneError(f"optimizer '{optimizer}' is not an optax optimiser")
    if steps < 1 or runs_per_step < 1:
        raise TuneError("steps and runs_per_step must be at least 1")
    inputs, cfg = device_arrays.run_arrays(run, config, names, TuneError)
    if objective == "supervised":
        device_arrays.require_ground_truth(inputs.mask, objective, TuneError)
    base = sizing.filter_params(config, run)
    for n in names:
        if not (math.isfinite(cur[n]) and cur[n] > 0):
            raise TuneError(f"start value of '{n}' must be positive and finite, got {cur[n]}")
    x = jnp.log(jnp.asarray([cur[n] for n in names], jnp.float32))
    opt, opt_state = _optimizer(optimizer, lr, optimizer_kwargs or {}, x)
    key = jax.random.key(config.filter.seed) if key is None else key
    history, losses = [np.exp(np.asarray(x, np.float64))], []
    t0 = time.perf_counter()
    for s in range(steps):
        keys = jax.random.split(key if crn else jax.random.fold_in(key, s), runs_per_step)
        (loss, status), g = _value_and_grad(x, keys, base, inputs, names, cfg, objective)
        maps.check_status(status, cfg, f"tune step {s}: ")
        if not np.all(np.isfinite(np.asarray(g))):
            raise TuneError(f"non-finite gradient at step {s} for "
                            f"{dict(zip(names, np.exp(np.asarray(x)).round(6)))}")
        updates, opt_state = opt.update(g, opt_state, x)
        x = optax.apply_updates(x, updates)
        losses.append(float(loss))
        history.append(np.exp(np.asarray(x, np.float64)))
        if progress is not None:
            progress(s + 1, steps)
        if on_step is not None:
            on_step(s + 1, float(loss), dict(zip(names, map(float, history[-1]))))
    values = {n: float(v) for n, v in zip(names, history[-1])}
    return TuneResult(names, values, np.stack(history), np.asarray(losses), objective,
                      time.perf_counter() - t0)
