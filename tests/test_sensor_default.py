"""The automatic ``[filter] ess_target`` (0) and ``proposal_draws`` ("auto"): picked by how a
run's local maps were made (``Run.sensor``), stored in Run files, reaching the filter, the live
API and the summary."""

import numpy as np
import pytest
from synthetic import make_run

from gslam_jax import choices
from gslam_jax.config import Config, apply_overrides
from gslam_jax.driver import sizing, slam
from gslam_jax.driver.online import Online
from gslam_jax.errors import ArgumentError
from gslam_jax.run import RunError, load_run, save_run


def _small(*overrides: str) -> Config:
    return apply_overrides(Config(), ["filter.particles=16", "map.margin=4", *overrides])


@pytest.mark.parametrize("sensor, target", [(None, 0.5), ("points", 0.5), ("stereo", 0.99)])
def test_the_run_sensor_picks_the_automatic_target(sensor, target):
    run, _ = make_run(steps=12)
    cfg = sizing.filter_config(_small(), run._replace(sensor=sensor))
    assert cfg.ess_target == target == choices.AUTO_ESS_TARGET.get(sensor or "points")
    assert sizing.filter_config(_small("filter.ess_target=0.7"),
                              run._replace(sensor=sensor)).ess_target == 0.7  # set: kept


def test_a_stereo_run_is_filtered_as_with_the_target_set_by_hand():
    """The resolved values reach the filter: sensor "stereo" under the automatic target and
    draws gives the poses of an unmarked run with ess_target = 0.99 and antithetic draws set,
    and not those of 0.5."""
    run, _ = make_run(steps=24)
    auto = slam.run_slam(run._replace(sensor="stereo"), _small())
    by_hand = slam.run_slam(run, _small("filter.ess_target=0.99",
                                        "filter.proposal_draws=antithetic"))
    points = slam.run_slam(run, _small())
    np.testing.assert_array_equal(auto.path, by_hand.path)
    assert not np.array_equal(auto.path, points.path)
    assert auto.resampled.sum() <= points.resampled.sum()


def test_sensor_round_trips_and_bad_values_are_named(tmp_path):
    run, _ = make_run(steps=12)
    save_run(tmp_path / "s.npz", run._replace(sensor="stereo"))
    assert load_run(tmp_path / "s.npz").sensor == "stereo"
    save_run(tmp_path / "n.npz", run)
    assert load_run(tmp_path / "n.npz").sensor is None
    fields = {k: v for k, v in run._asdict().items() if v is not None}
    np.savez(tmp_path / "bad.npz", **fields, sensor="lidar")
    with pytest.raises(RunError, match=r"bad\.npz: field 'sensor': expected one of points, "
                                       r"stereo, got lidar"):
        load_run(tmp_path / "bad.npz")


def test_online_takes_the_sensor():
    stereo, unmarked = Online(_small(), 20.0, sensor="stereo").cfg, Online(_small(), 20.0).cfg
    assert (stereo.ess_target, stereo.proposal_draws) == (0.99, "antithetic")
    assert (unmarked.ess_target, unmarked.proposal_draws) == (0.5, "independent")
    # [localmap] lattice = "auto": stereo local maps fused by push_points on the map's axes
    assert Online(_small(), 20.0, sensor="stereo").localmap.lattice == "map"
    assert Online(_small(), 20.0).localmap.lattice == "robot"
    with pytest.raises(ArgumentError, match="sensor must be one of points, stereo or None, got 'lidar'"):
        Online(_small(), 20.0, sensor="lidar")
