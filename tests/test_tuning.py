"""Differentiable tuning: the Scibior-Wood stop-gradient estimator against finite differences."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from synthetic import make_run

from gslam_jax import rbpf
from gslam_jax.config import Config, FilterSection, MapSection, MotionSection
from gslam_jax.driver import observations, sizing
from gslam_jax.rbpf.motion import MotionParams, apply_motion, log_density
from gslam_jax.tuning import gradient as TU
from gslam_jax.vo.localmap import LocalMapParams

LM = LocalMapParams(resolution=0.16, max_range=2.5, travel=1.0)


def _config(J, ratio=0.5, tempering="adaptive", **motion):
    return Config(filter=FilterSection(particles=J, unknown_cells="ignore", resample_ratio=ratio,
                                       tempering=tempering),
                  map=MapSection(margin=1.0), motion=MotionSection(**motion))


@pytest.fixture(scope="module")
def short_run():
    """10 frames, 5 local-map updates: every test here is about the estimator, not the size."""
    run, _ = make_run(seed=1, steps=10, drift=0.01, params=LM)
    return run


@jax.jit
def _scores(p: MotionParams, pose, u, eps):
    """The summed transition score's value and gradient, and the gradient of the summed motion
    log density of the poses the draws ``eps`` move ``pose`` to (one compilation for every
    parameter value)."""
    new = apply_motion(pose, u, eps, p)

    def score(q):
        return jnp.sum(TU.transition_score(eps, u, q))

    def dens(q):
        return jnp.sum(log_density(new, pose, u, q))
    return score(p), jax.grad(score)(p), jax.grad(dens)(p)


@pytest.mark.parametrize("alpha_cross", [0.0, 0.03])
def test_transition_score_is_the_motion_log_density_gradient(alpha_cross):
    """Zero in value; in gradient, d/dtheta log p_theta(x_t | x_{t-1}, u_t) of motion.py."""
    rng = np.random.default_rng(0)
    pose = jnp.asarray(rng.normal(size=(16, 3)), jnp.float32)
    u = jnp.asarray([0.4, 0.05, 0.2], jnp.float32)
    eps = jnp.asarray(rng.normal(size=(16, 3)), jnp.float32)
    p0 = MotionParams(jnp.float32(0.05), jnp.float32(0.02), jnp.float32(0.08),
                      jnp.float32(alpha_cross))
    value, g1, g2 = _scores(p0, pose, u, eps)
    assert float(value) == 0.0
    for a, b in zip(g1, g2):
        np.testing.assert_allclose(float(a), float(b), rtol=2e-3)
    assert (float(g1.alpha_cross) != 0.0) == (alpha_cross > 0)


def test_default_names_leave_out_a_term_switched_off():
    """alpha_cross is 0 by default (the paper's eq. 1): log space cannot start there, so the
    tuner's default names leave it out until it is given a positive value."""
    assert "alpha_cross" in TU.MOTION_PARAM_NAMES
    assert "alpha_cross" not in TU.default_names("loglik", {"alpha_cross": 0.0})
    assert "alpha_cross" in TU.default_names("supervised", {"alpha_cross": 0.01})
    # fallback_scale matters only on a run with fallback frames: tuned when named
    assert TU.default_names("loglik") == tuple(n for n in TU.MOTION_PARAM_NAMES
                                               if n != "fallback_scale")


def test_forward_values_equal_the_filter(short_run):
    config = _config(8)
    inputs, cfg = TU.make_inputs(short_run, config)
    inputs = inputs._replace(local_obs=observations.refine_observations(inputs.local_obs,
                                                                        inputs.obs))
    params = sizing.filter_params(config)
    key = jax.random.key(5)
    obj = TU.sw_objectives(key, params, inputs, cfg)
    out = rbpf.run_filter(key, params, inputs.controls, inputs.obs_index, inputs.local_obs, cfg,
                          inputs.start)
    np.testing.assert_allclose(float(obj.loglik), float(jnp.sum(out.infos.log_lik)), rtol=1e-6)


# XLA's CPU fusion emitters (its default) for the programs of a test whose time is their
# runtime, where tests/conftest.py has turned them off for the suite (the classic emitters
# compile faster but run these 7 x 256 filter runs slower; docs/notebook/test-suite.md).
RUNTIME_BOUND = ({"xla_cpu_use_fusion_emitters": True}
                 if "xla_cpu_use_fusion_emitters=false" in os.environ.get("XLA_FLAGS", "")
                 else None)


def test_gradient_matches_central_differences(short_run):
    """The estimator's gradient of the supervised objective agrees in sign and within 20% with
    central differences of the same objective under common random numbers, for each kind of
    parameter: the along-track motion noise alpha_d, the heading motion noise alpha_theta and
    the tempering constant beta_prev (ESS-gated resampling on, 3x too much motion noise so the
    gradient is well away from zero). alpha_theta_d enters the same heading std as alpha_theta
    (sigma_theta = alpha_theta_d |d| + alpha_theta |dtheta|) and its score, like every
    alpha's, is checked against the motion log density above; leaving it out saves two of the
    eight finite-difference runs of the filter. Fixed tempering: the adaptive exponent is held
    constant under differentiation (``gslam_jax.rbpf.tempering``), so its gradient leaves out
    how the exponent moves, which the finite differences include.

    The alphas' gradient is a score-function estimate (high variance): over 8 disjoint sets of
    32 runs of this 10-frame run, its relative standard error at 256 runs was about 8%
    (alpha_d) and 4% (alpha_theta), and beta_prev's 12%; the finite differences' 3%, 2% and
    10% (on the same random numbers, so the two err together). Hence 256 runs here.
    """
    J, K, h = 64, 256, 0.3
    names = ("alpha_d", "alpha_theta", "beta_prev")
    config = _config(J, ratio=0.5, tempering="fixed", alpha_d=0.15, alpha_theta_d=0.03,
                     alpha_theta=0.15)
    inputs, cfg = TU.make_inputs(short_run, config)
    base = sizing.filter_params(config)
    x = jnp.log(jnp.asarray([0.15, 0.15, 0.05], jnp.float32))
    keys = jax.random.split(jax.random.key(0), K)
    static = (names, cfg, "supervised")
    grad = TU._value_and_grad.lower(x, keys, base, inputs, *static).compile(
        compiler_options=RUNTIME_BOUND)
    _, g = grad(x, keys, base, inputs)
    f = jax.jit(TU.objective_fn, static_argnames=("names", "cfg", "objective")).lower(
        x, keys, base, inputs, *static).compile(compiler_options=RUNTIME_BOUND)
    d = len(names)
    vals = np.array([float(f(x + s, keys, base, inputs)[0])
                     for s in np.concatenate([h * np.eye(d), -h * np.eye(d)])])
    fd = (vals[:d] - vals[d:]) / (2 * h)
    g = np.asarray(g)
    assert np.all(np.sign(g) == np.sign(fd)), (g, fd)
    np.testing.assert_allclose(g, fd, rtol=0.2)


def test_tune_moves_towards_lower_loss_and_checks_input(short_run):
    config = _config(8)
    with pytest.raises(TU.TuneError, match="beta_prev"):
        TU.tune(short_run, config, "loglik", names=["alpha_d", "beta_prev"], steps=1)
    with pytest.raises(TU.TuneError, match="unknown parameter 'alpha'"):
        TU.tune(short_run, config, "supervised", names=["alpha"], steps=1)
    with pytest.raises(TU.TuneError, match="not an optax optimiser"):
        TU.tune(short_run, config, "supervised", optimizer="nope", steps=1)
    res = TU.tune(short_run, config, "supervised", optimizer="sgd", lr=0.5, steps=2,
                  names=["alpha_d"], start={"alpha_d": 0.3}, runs_per_step=1)
    assert res.history.shape == (3, 1) and np.all(np.isfinite(res.losses))
    assert res.values["alpha_d"] > 0 and res.values["alpha_d"] != 0.3


def test_tune_rejects_optimisers_needing_more_than_the_gradient(short_run):
    """lbfgs (value, grad, value_fn) and polyak_sgd (value) are refused before any filter run,
    naming the optimiser, not a TypeError mid-run."""
    config = _config(8)
    for name in ("lbfgs", "polyak_sgd"):
        with pytest.raises(TU.TuneError, match=f"optimizer '{name}' needs extra arguments"):
            TU.tune(short_run, config, "supervised", optimizer=name, steps=1,
                    names=["alpha_d"], runs_per_step=1)
    with pytest.raises(TU.TuneError, match="optimizer 'apply_updates' cannot be built"):
        TU.tune(short_run, config, "supervised", optimizer="apply_updates", steps=1)
    with pytest.raises(TU.TuneError, match="'constant_schedule' is not an optax optimiser"):
        TU.tune(short_run, config, "supervised", optimizer="constant_schedule", steps=1)


@pytest.mark.parametrize("name, kwargs, match", [
    ("lbfgs", {"memory_size": 0}, r"optimizer 'lbfgs' cannot be built as optax\.lbfgs\("
                                  r"learning_rate, \*\*optimizer_kwargs\): ValueError: "
                                  r"memory_size must be >= 1"),
    ("adamw", {"mask": {"a": True}}, r"optimizer 'adamw' cannot be initialised on the 1 tuned "
                                     r"parameter\(s\) with optimizer_kwargs "
                                     r"\{'mask': \{'a': True\}\}: ValueError"),
])
def test_tune_reports_optimiser_value_errors(short_run, name, kwargs, match):
    """A ValueError from the optimiser's arguments was a traceback, not a TuneError."""
    with pytest.raises(TU.TuneError, match=match):
        TU.tune(short_run, _config(8), "supervised", optimizer=name, steps=1,
                names=["alpha_d"], runs_per_step=1, optimizer_kwargs=kwargs)


def test_supervised_needs_a_frame_with_ground_truth(short_run):
    """No finite ground-truth frame would make the loss 0 whatever the parameters."""
    blind = short_run._replace(ground_truth=np.full_like(short_run.ground_truth, np.nan))
    with pytest.raises(TU.TuneError, match=r"no frame with a finite position \(x, y\)"):
        TU.tune(blind, _config(8), "supervised", steps=1, names=["alpha_d"], runs_per_step=1)


def test_supervised_uses_positions_only(short_run):
    """Ground truth with NaN headings: the loss is the squared position error, the same as with
    the headings known. Before, every frame was dropped and tune refused."""
    gt = short_run.ground_truth.copy()
    gt[:, 2] = np.nan
    kwargs = dict(steps=1, names=["alpha_d"], runs_per_step=1, key=jax.random.key(3))
    got = TU.tune(short_run._replace(ground_truth=gt), _config(8), "supervised", **kwargs)
    want = TU.tune(short_run, _config(8), "supervised", **kwargs)
    np.testing.assert_array_equal(got.losses, want.losses)
    np.testing.assert_array_equal(got.history, want.history)
