"""The fallback odometry's frames (``[motion] fallback_scale``): every std of eqs. 2-3 times the
scale on the frames a Run flags ``vo_failed``, in the batch run, ``Online``, the search and the
tuner (the tiled reference's agreement with it: ``test_tiled``); a scale of 1 is the filter as
before."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from synthetic import make_run

from gslam_jax import rbpf
from gslam_jax.app.cli import main
from gslam_jax.config import Config, ConfigError, FilterSection, MotionSection
from gslam_jax.driver import sizing, slam
from gslam_jax.driver.observations import refine_observations
from gslam_jax.driver.online import Online
from gslam_jax.rbpf.motion import MotionParams, apply_motion, motion_stds, scaled
from gslam_jax.run import save_run
from gslam_jax.tuning import gradient as TU

FAILED = slice(20, 26)  # the frames of a VO failure burst in the runs below


@pytest.fixture(scope="module")
def failing_run():
    run, _ = make_run(seed=2, steps=50)
    failed = np.zeros(run.num_frames, bool)
    failed[FAILED] = True
    return run._replace(vo_failed=failed)


def _config(scale: float, particles: int = 8) -> Config:
    return Config(filter=FilterSection(particles=particles, seed=1),
                  motion=MotionSection(fallback_scale=scale))


@pytest.fixture(scope="module")
def slam_of(failing_run):
    """``slam_of(scale, flagged=True)``: slam.run_slam of the failing run (without its
    ``vo_failed`` flags when not ``flagged``) with ``_config(scale)``, run once per module and
    shared by the tests below."""
    done = {}

    def run(scale: float, flagged: bool = True):
        if (scale, flagged) not in done:
            run_ = failing_run if flagged else failing_run._replace(vo_failed=None)
            done[scale, flagged] = slam.run_slam(run_, _config(scale))
        return done[scale, flagged]
    return run


def test_scaled_multiplies_every_std_and_draw():
    p = MotionParams(0.05, 0.01, 0.04, 0.02)
    u = jnp.array([[0.3, 0.05, 0.1], [0.0, 0.0, 0.2], [0.4, 0.0, 0.0]])
    d1, sd1, st1 = motion_stds(u, p)
    d3, sd3, st3 = motion_stds(u, scaled(p, 3.0))
    np.testing.assert_allclose(d3, d1)
    np.testing.assert_allclose(sd3, 3 * sd1, rtol=1e-6)
    np.testing.assert_allclose(st3, 3 * st1, rtol=1e-6)
    pose = jnp.array([1.0, -2.0, 0.7])
    eps = jnp.array([[0.8, -1.3, 0.5]] * 3)
    still = apply_motion(pose, u, jnp.zeros_like(eps), p)
    np.testing.assert_allclose(apply_motion(pose, u, eps, scaled(p, 3.0)) - still,
                               3 * (apply_motion(pose, u, eps, p) - still), atol=1e-6)


def test_fallback_frames_marks_the_fallback_frames(failing_run):
    assert sizing.fallback_frames(failing_run, _config(1.0)) is None  # as before
    assert sizing.fallback_frames(failing_run._replace(vo_failed=None), _config(3.0)) is None
    want = np.zeros(failing_run.num_frames, bool)
    want[FAILED] = True
    np.testing.assert_array_equal(sizing.fallback_frames(failing_run, _config(3.0)), want)
    np.testing.assert_array_equal(sizing.fallback_frames(failing_run, _config(1.0), keep=True),
                                  want)
    assert float(sizing.filter_params(_config(3.0)).motion.fallback_scale) == 3.0
    for bad in (0.0, 1e4):
        with pytest.raises(ConfigError, match=r"\[motion\] fallback_scale must be in \(0, 1000\]"):
            _config(bad).validate()


@pytest.mark.parametrize("proposal", ["motion", "informed"])
def test_the_particles_spread_by_the_scaled_noise(proposal):
    """No update: after T frames each particle's heading has moved by the sum of its draws
    times each frame's sigma_theta (eq. 3), so over many particles its variance is the sum of
    the frames' (s_t sigma_theta)^2; the informed proposal carries that sum in its prior
    covariance (linearised, and exact for the heading)."""
    T = 12
    J = 4096 if proposal == "motion" else 16  # the variance over many; the covariance: each
    p = MotionParams(0.05, 0.02, 0.1)
    u = jnp.tile(jnp.array([0.5, 0.0, 0.1], jnp.float32), (T, 1))
    fallback = np.zeros(T, bool)
    fallback[3:6] = True
    s = np.where(fallback, 4.0, 1.0)
    sigma = 0.02 * 0.5 + 0.1 * 0.1
    want = float(np.sum((s * sigma) ** 2))
    cfg = rbpf.FilterConfig(J, (16, 16), (-1.3, -1.3), 0.16, 4, proposal=proposal).validate()
    params = rbpf.FilterParams(motion=p._replace(fallback_scale=4.0))
    state, _ = rbpf.scan_frames(rbpf.init(cfg), rbpf.frame_keys(jax.random.key(0), T), u,
                                -jnp.ones(T, jnp.int32), jnp.zeros((1, 4, 4, 2)), params, cfg,
                                fallback=jnp.asarray(fallback))
    if proposal == "informed":
        np.testing.assert_allclose(np.asarray(state.prior_cov[:, 2, 2]), want, rtol=1e-5)
    else:
        heading = np.asarray(state.pose[:, 2], np.float64)
        assert np.var(heading) == pytest.approx(want, rel=0.08)  # 8 % = 5 standard errors
        assert abs(np.var(heading) - T * sigma ** 2) > 0.5 * want  # not the unscaled spread


def test_a_scale_of_one_is_the_filter_as_before(failing_run, slam_of):
    plain = slam_of(3.0, flagged=False)
    ones = slam_of(1.0)
    scaled_run = slam_of(3.0)
    np.testing.assert_array_equal(ones.path, plain.path)
    before = failing_run.obs_index[:FAILED.start] >= 0
    # the same up to the burst, where the draws are the same; different after it
    np.testing.assert_array_equal(scaled_run.best_pose[:FAILED.start][before],
                                  plain.best_pose[:FAILED.start][before])
    assert np.max(np.abs(scaled_run.path - plain.path)) > 1e-4


def test_online_reproduces_the_batch_run_with_fallback_frames(failing_run, slam_of):
    config = _config(3.0)
    res = slam_of(3.0)
    live = Online(config, filter_config=slam.run_filter_config(failing_run, config))
    for t in range(failing_run.num_frames):
        m = failing_run.obs_index[t]
        out = live.push(failing_run.controls[t], failing_run.local_maps[m] if m >= 0 else None,
                        failing_run.timestamps[t], vo_failed=bool(failing_run.vo_failed[t]))
        np.testing.assert_array_equal(out.pose, res.best_pose[t])
    np.testing.assert_allclose(live.path(), res.path, rtol=0, atol=1e-9)


def test_the_tuner_runs_the_filter_with_the_scale(failing_run):
    """The Scibior-Wood objective's forward value is the filter's evidence with the same
    scaled frames, and differs from the unscaled one."""
    config = dataclasses.replace(_config(3.0), filter=FilterSection(particles=8, seed=1,
                                                                      resample_ratio=0.0))
    inputs, cfg = TU.make_inputs(failing_run, config)
    assert inputs.fallback is not None
    inputs = inputs._replace(local_obs=refine_observations(inputs.local_obs, inputs.obs))
    params = sizing.filter_params(config)
    key = jax.random.key(5)
    obj = TU.sw_objectives(key, params, inputs, cfg)
    out = rbpf.run_filter(key, params, inputs.controls, inputs.obs_index, inputs.local_obs,
                          cfg, inputs.start, inputs.lattice_headings, inputs.fallback)
    # the same frames at a scale of 1 (the scale is a traced parameter: no second compilation)
    unscaled = rbpf.run_filter(key, params._replace(motion=params.motion._replace(
        fallback_scale=jnp.float32(1.0))), inputs.controls, inputs.obs_index, inputs.local_obs,
        cfg, inputs.start, inputs.lattice_headings, inputs.fallback)
    evidence = float(jnp.sum(out.infos.log_lik))
    np.testing.assert_allclose(float(obj.loglik), evidence, rtol=1e-6)
    assert abs(evidence - float(jnp.sum(unscaled.infos.log_lik))) > 1e-3


def test_gslam_run_reports_the_fallback_frames_and_their_scale(failing_run, tmp_path, capsys):
    path = tmp_path / "failing.npz"
    save_run(path, failing_run)
    assert main(["run", str(path), "--set", "filter.particles=8", "--set",
                 "motion.fallback_scale=2.5", "--no-map-check", "--out", str(tmp_path / "out")]) == 0
    assert ("note: 6 frames came from the fallback odometry (VO failed), their motion noise "
            "2.5x the VO's") in capsys.readouterr().out
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["vo_failures"] == 6 and summary["fallback_scale"] == 2.5


def test_a_search_over_the_scale_scores_each_value_as_the_filter_does(failing_run, slam_of):
    """``fallback_scale`` is a searchable setting: each searched value's objective is a
    plain filter run's with that value in the config (slam.run_slam, not the batched
    evaluation), the value 1 included, where the run carries the flags at a scale of 1."""
    from gslam_jax.tuning import space as SP
    from gslam_jax.tuning.search import search

    config = _config(1.0)
    space = SP.SearchSpace(("fallback_scale",), (1.0,), (8.0,), (False,))
    values = np.array([[1.0], [4.0], [8.0]])
    res = search(failing_run, config, space, objective="loglik", values=values)
    got = {float(v[0]): float(o) for v, o in zip(res.values, res.objective)}
    for v in (1.0, 4.0, 8.0):
        want = float(np.sum(slam_of(v).log_lik))
        assert got[v] == pytest.approx(want, rel=1e-4, abs=1e-3), v
    assert len({round(o, 3) for o in got.values()}) == 3  # the scale changes the evidence
    with pytest.raises(SP.SearchError, match="fallback_scale .* this run has none"):
        search(failing_run._replace(vo_failed=None), config, space, objective="loglik",
               values=values)


def test_the_tuner_differentiates_the_scale(failing_run):
    """The Scibior-Wood gradient of the evidence reaches ``fallback_scale`` through the
    scaled frames' transition scores: non-zero with the burst before later updates, exactly 0
    when only frames after the last update are flagged (they change no weight). The default
    names leave it out, and naming it on a run without such frames is a TuneError."""
    config = _config(2.0)
    names = ("fallback_scale",)
    x = jnp.log(jnp.asarray([2.0], jnp.float32))
    keys = jax.random.split(jax.random.key(4), 2)
    T = failing_run.num_frames
    quiet = failing_run._replace(obs_index=np.where(np.arange(T) < T - 4,
                                                    failing_run.obs_index, -1))
    late = np.zeros(T, bool)
    late[T - 4:] = True
    grads = []
    for run in (quiet, quiet._replace(vo_failed=late)):
        inputs, cfg = TU.make_inputs(run, config)
        base = sizing.filter_params(config)
        (_, _), g = TU._value_and_grad(x, keys, base, inputs, names, cfg, "loglik")
        grads.append(float(g[0]))
    assert grads[0] != 0.0 and np.isfinite(grads[0])
    assert grads[1] == 0.0
    assert "fallback_scale" not in TU.default_names("loglik")
    with pytest.raises(TU.TuneError, match="fallback_scale .* this run has none"):
        TU.tune(failing_run._replace(vo_failed=None), config, names=names, steps=1)
