"""The dense filter on a small hand-built world with known truth."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from synthetic import World, make_run

from gslam_jax import filter as gf
from gslam_jax import slam
from gslam_jax.cells import obs_from_stats
from gslam_jax.config import Config, FilterSection, MotionSection
from gslam_jax.localmap import LocalMapParams, points_to_stats

RES = 0.16
LM = LocalMapParams(resolution=RES, max_range=5.0, cells=64)


def _cfg(J, mode="ignore", **kw):
    return gf.FilterConfig(num_particles=J, map_shape=(256, 256), map_origin=(-20.48, -20.48),
                           resolution=RES, local_size=64, unknown_cells=mode, **kw)


def _local_obs(world, pose, seed):
    pts = world.observe(np.asarray(pose, float), np.random.default_rng(seed), n=30000)
    stats, _ = points_to_stats(pts, LM)
    return jnp.asarray(obs_from_stats(stats, 1e-6), jnp.float32)


@pytest.mark.parametrize("mode", ["ignore", "sample"])
def test_particle_nearest_truth_gains_weight(mode):
    """First observation builds the same map for all particles; the second, taken from the true
    pose, must favour the particle nearest the truth over ones displaced by VO drift."""
    world = World(3)
    truth = np.array([0.3, -0.2, 0.4])
    J = 9
    cfg = _cfg(J, mode, resample_ratio=0.0)
    params = gf.FilterParams()
    state = gf.init(cfg, jnp.asarray(truth, jnp.float32))
    noise = gf.update_noise(jax.random.key(0), cfg)
    state, _ = gf.update(state, _local_obs(world, truth, 1), noise, params, cfg)
    offsets = np.array([[0, 0, 0], [0.5, 0, 0], [-0.5, 0, 0], [0, 0.5, 0], [0, -0.5, 0],
                        [0.3, 0.3, 0.05], [0, 0, 0.1], [0, 0, -0.1], [1.0, 0.0, 0.0]])
    state = state._replace(pose=jnp.asarray(truth + offsets, jnp.float32))
    state, info = gf.update(state, _local_obs(world, truth, 2), noise, params, cfg)
    w = np.exp(np.asarray(info.log_w))
    assert int(np.argmax(w)) == 0
    assert w[0] > 0.5
    assert w[0] > 3 * np.sort(w)[-2]


@pytest.mark.parametrize("mode", ["ignore", "sample"])
def test_without_map_updates_the_weights_stay_uniform(mode):
    run, _ = make_run(seed=1, steps=30)
    cfg = _cfg(16, mode, update_map=False)
    obs = jnp.asarray(slam.local_observations(run, 1e-6))
    out = gf.run_filter(jax.random.key(0), gf.FilterParams(), jnp.asarray(run.controls, jnp.float32),
                        jnp.asarray(run.obs_index), obs, cfg)
    np.testing.assert_allclose(np.exp(np.asarray(out.infos.log_w)), 1 / 16, rtol=1e-5)
    assert not np.asarray(out.infos.resampled).any()


def _config(J=32, mode="sample", seed=0):
    return dataclasses.replace(Config(), filter=FilterSection(particles=J, unknown_cells=mode, seed=seed),
                               motion=MotionSection(alpha_theta_d=0.02))


def test_same_seed_is_bit_identical_and_seeds_differ():
    run, _ = make_run(seed=2, steps=40)
    a = slam.run_slam(run, _config(seed=5))
    b = slam.run_slam(run, _config(seed=5), chunk=7)  # chunking must not change anything
    c = slam.run_slam(run, _config(seed=6))
    np.testing.assert_array_equal(a.best_path, b.best_path)
    np.testing.assert_array_equal(a.ess, b.ess)
    np.testing.assert_array_equal(a.kmap, b.kmap)
    assert not np.array_equal(a.best_path, c.best_path)


def test_slam_corrects_vo_heading_drift_on_a_loop():
    run, _ = make_run(seed=4, steps=80, drift=0.004)
    res = slam.run_slam(run, _config(J=64))
    gt = run.ground_truth[:, :2]
    vo_err = np.linalg.norm(res.vo_path[:, :2] - gt, axis=1)
    slam_err = np.linalg.norm(res.best_path[:, :2] - gt, axis=1)
    assert res.resampled.any()
    assert vo_err[-1] > 0.8
    assert slam_err[-1] < 0.5 * vo_err[-1]
    assert res.extent_violations == 0


def test_windows_leaving_the_map_are_counted_not_wrapped():
    run, _ = make_run(seed=1, steps=20)
    cfg = gf.FilterConfig(num_particles=4, map_shape=(112, 112), map_origin=(-2.0, -9.0),
                          resolution=RES, local_size=64, unknown_cells="ignore")
    obs = jnp.asarray(slam.local_observations(run, 1e-6))
    out = gf.run_filter(jax.random.key(0), gf.FilterParams(), jnp.asarray(run.controls, jnp.float32),
                        jnp.asarray(run.obs_index), obs, cfg)
    assert int(np.sum(out.infos.extent_violations)) > 0


def test_empty_local_maps_leave_weights_unchanged_and_are_counted():
    run, _ = make_run(seed=1, steps=20)
    run = run._replace(local_maps=np.zeros_like(run.local_maps))
    res = slam.run_slam(run, _config(J=8))
    assert res.empty_observations == run.num_local_maps
    assert not res.resampled.any()
    np.testing.assert_allclose(res.ess, 8.0, rtol=1e-5)
