"""run_slam guards: NaN weights stop the run naming the frame; particle maps that cannot fit in
memory are a ConfigError before anything is allocated; the variance floor defaults positive."""

import dataclasses

import jax
import numpy as np
import pytest
from synthetic import make_run

from gslam_jax.config import Config, ConfigError, FilterSection, MapSection
from gslam_jax.driver import chunk_checks, observations, sizing, slam
from gslam_jax.errors import InputError
from gslam_jax.rbpf import cells, maps
from gslam_jax.run import RunError


def _small_config(**map_values) -> Config:
    return Config(filter=FilterSection(particles=8), map=MapSection(**map_values))


def test_zero_variance_cells_with_zero_floor_raise_naming_the_frame():
    """Before: every log weight NaN from the second update on, no resampling, no error."""
    run, _ = make_run(steps=15)
    maps = run.local_maps.copy()
    L = maps.shape[1]
    maps[:, L // 2 - 2:L // 2 + 2, L // 2 - 2:L // 2 + 2] = [5.0, 0.0, 0.0]  # 5 heights of 0 m
    run = run._replace(local_maps=maps)
    config = _small_config(min_variance=0.0)  # built directly: validate() now refuses it
    updates = np.flatnonzero(run.obs_index >= 0)
    m = run.obs_index[updates[1]]
    with pytest.raises(chunk_checks.WeightError,
                       match=rf"frame {updates[1]}: the filter cannot weigh "
                             rf"local map {m}: the update with it left "
                             rf"non-finite particle weights \(ESS nan, evidence "
                             rf"\(log-likelihood\) nan, not finite\); check "
                             rf"local map {m}'s statistics") as err:
        slam.run_slam(run, config)
    assert "min_variance" not in str(err.value)  # config validation already requires it > 0
    res = slam.run_slam(run, _small_config())  # the default floor: finite weights throughout
    assert np.isfinite(res.ess).all() and np.isfinite(res.log_lik).all()


def test_obs_from_stats_default_floor_is_positive():
    k, S = cells.obs_from_stats(np.array([4.0, 0.0, 0.0]))
    assert k == 3 and S == pytest.approx(3e-6)


def test_maps_larger_than_memory_are_a_config_error_before_allocating(monkeypatch):
    run, _ = make_run(steps=15)
    config = dataclasses.replace(Config(), filter=FilterSection(particles=10 ** 7))

    def no_alloc(*args, **kwargs):
        raise AssertionError("the particle maps were allocated")

    monkeypatch.setattr(slam.rbpf, "init", no_alloc)
    with pytest.raises(ConfigError, match=r"the particle maps need [\d.]+ GiB \(10000000 "
                                          r"particles x \d+ x \d+ cells .* more than this "
                                          r"machine's .*fewer \[filter\] particles, a coarser "
                                          r"\[map\] resolution, a smaller \[map\] margin or "
                                          r"\[map\] store = \"shared\""):
        slam.run_slam(run, config)


@pytest.mark.parametrize("unknown_cells", ["ignore", "sample"])
def test_map_memory_check_against_a_given_budget(unknown_cells):
    run, _ = make_run(steps=15)
    config = Config(filter=FilterSection(particles=8, unknown_cells=unknown_cells))
    cfg = sizing.filter_config(config, run)
    H, W = cfg.map_shape
    need = maps.map_bytes(cfg)
    # k and S float32; "sample" mode adds two uint32 known-cell bit words per 8 x 8 block and
    # an int32 count per segment of 4 blocks in a row of blocks
    bits = ((H // 8) * ((W // 8) * 2 * 4 + -(-(W // 8) // 4) * 4)
            if unknown_cells == "sample" else 0)
    assert need == 8 * (H * W * 2 * 4 + bits)
    allocated = maps.init(cfg)  # what the store holds, less its [2] written-rows bounds
    assert need == sum(x.nbytes for x in jax.tree.leaves(allocated)) - allocated.rows.nbytes
    maps.check_memory(cfg, available=need)
    with pytest.raises(ConfigError, match="the particle maps need"):
        maps.check_memory(cfg, available=need - 1)


def test_weight_error_is_an_input_error():
    """The CLI prints InputErrors without a traceback; WeightError reports unweighable data."""
    assert issubclass(chunk_checks.WeightError, InputError)


def test_observations_beyond_float32_are_a_run_error_naming_the_local_map():
    """Statistics finite in float64 whose (k, S) overflow float32: before, inf observations
    reached the filter (non-finite weights or silently wrong maps)."""
    run, _ = make_run(steps=15)
    updates = np.flatnonzero(run.obs_index >= 0)
    t, m = int(updates[1]), int(run.obs_index[updates[1]])
    maps = run.local_maps.copy()
    maps[m, 4, 5] = [3.0, 3e19, 3.01e39]  # S = 2.71e39: finite in float64, inf in float32
    run = run._replace(local_maps=maps)
    match = (rf"field 'local_maps': local map {m} \(frame {t}\), cell \(4, 5\) \(1 cells in "
             rf"all\): .* beyond float32.*check that local map's statistics")
    with pytest.raises(RunError, match=match):
        observations.local_observations(run, 1e-6)
    with pytest.raises(RunError, match=match):
        slam.run_slam(run, _small_config())
