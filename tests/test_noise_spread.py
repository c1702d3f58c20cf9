"""Each particle's own motion noise (``[motion] noise_spread``): the factors it starts with, that
each particle moves with its own, that resampling carries the factor with the particle, and that
the filter's weights pick the factor a log's drift calls for, from either side."""

from __future__ import annotations

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from synthetic import make_run

from gslam_jax import rbpf
from gslam_jax.app.cli import main
from gslam_jax.app.compare import compare
from gslam_jax.config import Config, ConfigError, FilterSection, MotionSection
from gslam_jax.driver import slam
from gslam_jax.driver.online import Online
from gslam_jax.rbpf.motion import MotionParams, apply_motion, particle_scales
from gslam_jax.run import save_run


@pytest.mark.parametrize("J, spread", [(8, 8.0), (7, 16.0), (1, 4.0), (200, 8.0)])
def test_particle_scales_are_stratified_cubes_in_antithetic_pairs(J, spread):
    s = np.asarray(particle_scales(J, spread), np.float64)
    P = (J + 1) // 2
    # spread ** (u ** 3), u the midpoints of P equal steps of [-1, 1], written out independently
    edges = np.linspace(-1.0, 1.0, P + 1)
    want = spread ** (((edges[:-1] + edges[1:]) / 2) ** 3)
    np.testing.assert_allclose(s[:P], want, rtol=1e-6)
    np.testing.assert_allclose(s[P:], want[:J - P], rtol=1e-6)  # row j + P is row j's pair
    assert s.min() > 1 / spread and s.max() < spread
    near = np.abs(np.log(s[:P]) / math.log(spread)) <= 1 / 8  # |u| <= 1/2
    assert near.mean() == pytest.approx(0.5, abs=1 / P + 1e-9)


def _state(J: int, noise_scale) -> rbpf.FilterState:
    cfg = rbpf.FilterConfig(num_particles=J, map_shape=(64, 64), map_origin=(-5.0, -5.0),
                            resolution=0.16, local_size=16, noise_spread=4.0)
    state = rbpf.init(cfg, jnp.array([0.5, -0.2, 0.3]))
    return state._replace(noise_scale=jnp.asarray(noise_scale, jnp.float32)), cfg


@pytest.mark.parametrize("fallback", [False, True])
def test_each_particle_moves_with_its_own_noise(fallback):
    scales = [0.25, 1.0, 2.0, 3.5]
    state, cfg = _state(4, scales)
    params = rbpf.FilterParams(motion=MotionParams(0.05, 0.02, 0.04, 0.01, fallback_scale=3.0))
    u = jnp.array([0.4, 0.03, 0.1])
    key = jax.random.key(5)
    moved, _ = rbpf.step(key, state, u, None, params, cfg,
                         fallback=jnp.bool_(True) if fallback else False)
    eps = rbpf.motion_noise(jax.random.split(key)[0], cfg)  # the draws ``step`` makes
    m = params.motion
    for j, c in enumerate(scales):  # one particle at a time, its alphas scaled by hand
        c = c * (3.0 if fallback else 1.0)
        own = MotionParams(m.alpha_d * c, m.alpha_theta_d * c, m.alpha_theta * c,
                           m.alpha_cross * c)
        np.testing.assert_allclose(moved.pose[j], apply_motion(state.pose[j], u, eps[j], own),
                                   rtol=1e-5, atol=1e-6)


def test_resampling_carries_each_particle_s_noise_with_it():
    state, cfg = _state(6, [0.5, 0.7, 1.0, 1.5, 2.0, 3.0])
    log_w = jnp.log(jnp.array([1e-6, 1e-6, 0.5, 1e-6, 0.5, 1e-6]))
    state = state._replace(log_w=log_w - jax.nn.logsumexp(log_w),
                           pose=jnp.arange(18, dtype=jnp.float32).reshape(6, 3))
    new, anc, done = rbpf.resample(state, jnp.linspace(0.05, 0.95, 6), cfg)
    assert bool(done) and set(np.asarray(anc).tolist()) == {2, 4}
    np.testing.assert_array_equal(new.noise_scale, np.asarray(state.noise_scale)[anc])
    np.testing.assert_array_equal(new.pose, np.asarray(state.pose)[anc])
    # the reported factor: the weighted geometric mean
    np.testing.assert_allclose(rbpf.mean_noise_scale(state), math.sqrt(1.0 * 2.0), rtol=1e-4)


def test_without_a_spread_the_state_has_no_factors_and_reports_one():
    cfg = rbpf.FilterConfig(num_particles=4, map_shape=(64, 64), map_origin=(-5.0, -5.0),
                            resolution=0.16, local_size=16)
    state = rbpf.init(cfg)
    assert state.noise_scale is None and float(rbpf.mean_noise_scale(state)) == 1.0
    with pytest.raises(ValueError, match="noise_spread"):
        cfg._replace(noise_spread=0.5).validate()


@pytest.fixture(scope="module")
def drifting_run():
    """VO with a heading bias of 0.008 rad per metre travelled (``make_run``: 0.004 rad per
    0.5 m step)."""
    return make_run(seed=2, steps=60)[0]


@pytest.mark.parametrize("alpha, lower, upper", [(0.3, 0.0, 0.3), (0.003, 1.5, 16.0)])
def test_the_weights_pick_the_noise_the_drift_calls_for(drifting_run, alpha, lower, upper):
    """Given heading noise of 0.3 rad per metre (far too wide for the run's 0.008) the surviving
    particles' factor falls under 0.3; given 0.003 (too narrow to follow the drift) it rises
    over 1.5, for two filter seeds each."""
    for seed in (1, 2):
        config = Config(filter=FilterSection(particles=64, seed=seed),
                        motion=MotionSection(alpha_d=alpha / 3, alpha_theta_d=alpha,
                                             alpha_theta=alpha, noise_spread=16.0))
        res = slam.run_slam(drifting_run, config)
        assert res.noise_scale[0] == pytest.approx(1.0, rel=1e-3)  # no update at frame 0
        assert lower < res.noise_scale[-1] < upper, (seed, res.noise_scale[::10])


def test_config_refuses_a_spread_under_one_and_the_tiled_comparison_refuses_any(drifting_run):
    with pytest.raises(ConfigError, match=r"\[motion\] noise_spread"):
        Config(motion=MotionSection(noise_spread=0.5)).validate()
    config = Config(motion=MotionSection(noise_spread=4.0))
    with pytest.raises(ConfigError, match="noise_spread"):
        compare(drifting_run, config, particles=4, verbose=False)


def test_gslam_run_reports_the_surviving_factor(drifting_run, tmp_path, capsys):
    path = tmp_path / "drift.npz"
    save_run(path, drifting_run)
    out = tmp_path / "out"
    assert main(["run", str(path), "--set", "filter.particles=16", "--set",
                 "motion.noise_spread=4", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    trace = np.load(out / "trace.npz")
    assert summary["noise_spread"] == 4.0
    assert summary["final_noise_scale"] == pytest.approx(float(trace["noise_scale"][-1]))
    assert 1 / 4 < summary["final_noise_scale"] < 4
    assert (f"motion noise: the particles' factor on the [motion] alphas ended at "
            f"{summary['final_noise_scale']:.3g}") in capsys.readouterr().out


def test_online_holds_each_particle_s_factor_as_the_batch_run_does(drifting_run):
    # the settings of the `gslam run` test above but the seed: its compiled filter serves
    config = Config(filter=FilterSection(particles=16, seed=1),
                    motion=MotionSection(noise_spread=4.0))
    res = slam.run_slam(drifting_run, config)
    live = Online(config, filter_config=slam.run_filter_config(drifting_run, config))
    for t in range(drifting_run.num_frames):
        m = drifting_run.obs_index[t]
        live.push(drifting_run.controls[t], drifting_run.local_maps[m] if m >= 0 else None,
                  drifting_run.timestamps[t])
    p = live.particles()
    assert p.noise_scale.shape == (16,)
    np.testing.assert_allclose(np.exp(np.sum(p.weight * np.log(p.noise_scale))),
                               res.noise_scale[-1], rtol=1e-4)
    plain = Online(Config(filter=FilterSection(particles=4)))
    assert plain.particles().noise_scale is None
