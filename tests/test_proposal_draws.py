"""``[filter] proposal_draws``: antithetic pairs of the proposals' standard normals."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats
from synthetic import make_run

from gslam_jax import rbpf
from gslam_jax.config import Config, ConfigError, apply_overrides
from gslam_jax.driver import observations, sizing

_make_run = functools.lru_cache(make_run)


@pytest.mark.parametrize("J", [8, 9])
def test_antithetic_rows_pair_and_each_row_is_standard_normal(J):
    keys = jax.random.split(jax.random.key(3), 400)
    z = np.asarray(jax.vmap(lambda k: rbpf.standard_normals(k, (J, 2), "antithetic"))(keys))
    half = (J + 1) // 2
    np.testing.assert_array_equal(z[:, half:], -z[:, :J - half])
    # every row, over independent keys, is N(0, 1) in each coordinate (scipy's KS test)
    for j in range(J):
        for d in range(2):
            assert stats.kstest(z[:, j, d], "norm").pvalue > 1e-4, (j, d)
    # the independent rows share no such structure
    ind = np.asarray(rbpf.standard_normals(keys[0], (J, 2), "independent"))
    assert abs(ind.sum()) > 1e-3


def _mean_heading_error(draws: str) -> float:
    """Largest gap, over frames, between the particles' mean heading and the VO's, on a run
    whose weights stay flat (no map updates)."""
    run, _ = _make_run(seed=1, steps=30)
    cfg = rbpf.FilterConfig(num_particles=16, map_shape=(256, 256), map_origin=(-20.48, -20.48),
                            resolution=0.16, local_size=64, update_map=False,
                            proposal_draws=draws)
    controls = jnp.asarray(run.controls, jnp.float32)
    out = rbpf.run_filter(jax.random.key(0), rbpf.FilterParams(), controls,
                          jnp.asarray(run.obs_index),
                          jnp.asarray(observations.local_observations(run, 1e-6)), cfg)
    np.testing.assert_allclose(np.exp(np.asarray(out.infos.log_w)), 1 / 16, rtol=1e-5)
    heading = np.asarray(out.infos.pose)[..., 2]            # [T, J]
    vo = np.cumsum(np.asarray(run.controls, np.float64)[:, 2])
    return float(np.abs(heading.mean(1) - vo).max())


def test_antithetic_draws_keep_the_mean_heading_on_the_vo_where_weights_are_flat():
    # the heading noise (eq. 3) depends on the control only, so each pair cancels exactly
    assert _mean_heading_error("antithetic") < 1e-5
    assert _mean_heading_error("independent") > 1e-3


def test_the_config_names_a_bad_proposal_draws():
    assert apply_overrides(Config(), ["filter.proposal_draws=antithetic"]).filter \
        .proposal_draws == "antithetic"
    with pytest.raises(ConfigError, match="proposal_draws"):
        apply_overrides(Config(), ["filter.proposal_draws=paired"])
    with pytest.raises(ValueError, match="proposal_draws"):
        rbpf.FilterConfig(1, (64, 64), (0.0, 0.0), 0.16, 8, proposal_draws="paired").validate()


def test_auto_draws_follow_the_runs_sensor():
    assert Config().filter.proposal_draws == "auto"
    assert sizing.resolve_proposal_draws("auto", "stereo") == "antithetic"
    assert sizing.resolve_proposal_draws("auto", "points") == "independent"
    assert sizing.resolve_proposal_draws("auto", None) == "independent"
    assert sizing.resolve_proposal_draws("independent", "stereo") == "independent"
    with pytest.raises(ConfigError, match="sensor"):
        sizing.resolve_proposal_draws("auto", "lidar")
    run, _ = _make_run(seed=1, steps=10)
    stereo = run._replace(sensor="stereo")
    assert sizing.filter_config(Config(), stereo).proposal_draws == "antithetic"
    assert sizing.filter_config(Config(), run).proposal_draws == "independent"
    with pytest.raises(ValueError, match="resolved"):
        rbpf.FilterConfig(1, (64, 64), (0.0, 0.0), 0.16, 8, proposal_draws="auto").validate()
    with pytest.raises(ValueError, match="resolved"):
        rbpf.standard_normals(jax.random.key(0), (4, 2), "auto")
