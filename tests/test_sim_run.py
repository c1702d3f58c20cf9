"""simulate_run: a valid, reproducible Run with ground truth and the true noise recorded."""

from __future__ import annotations

import numpy as np
import pytest

from gslam_jax.datasets.sim import simulate_run
from gslam_jax.errors import ArgumentError
from gslam_jax.vo.localmap import LocalMapParams
from gslam_jax.run import validate_run

PARAMS = LocalMapParams(resolution=0.16, max_range=8.0)


@pytest.fixture(scope="module")
def short_run():
    calls = []
    run, info = simulate_run("mars-yard-a", seed=2, params=PARAMS, max_frames=120,
                             progress=lambda done, total: calls.append((done, total)))
    return run, info, calls


def test_run_is_valid_and_complete(short_run) -> None:
    run, info, calls = short_run
    validate_run(run)
    T = run.num_frames
    assert T == 120
    assert run.resolution == PARAMS.resolution
    assert run.local_maps.shape[1:] == (PARAMS.size, PARAMS.size, 3)
    assert run.obs_index[0] == 0 and run.num_local_maps >= 2
    assert run.ground_truth.shape == (T, 3) and run.vo_failed.shape == (T,)
    np.testing.assert_allclose(run.initial_pose, run.ground_truth[0])
    np.testing.assert_allclose(run.vo_poses()[0], run.ground_truth[0])
    assert calls[-1] == (T, T)
    assert info.vo_noise.alpha_d > 0 and info.survey_frames[0] == 5
    np.testing.assert_allclose(info.survey_points, run.ground_truth[info.survey_frames, :2])
    assert info.points_per_frame > 1000


def test_run_is_reproducible_from_its_seed(short_run) -> None:
    run, info, _ = short_run
    again, info2 = simulate_run("mars-yard-a", seed=2, params=PARAMS, max_frames=120)
    for name in ("controls", "obs_index", "local_maps", "ground_truth", "vo_failed"):
        np.testing.assert_array_equal(getattr(run, name), getattr(again, name), err_msg=name)
    assert info.world.fingerprint() == info2.world.fingerprint()
    other, _ = simulate_run("mars-yard-a", seed=3, params=PARAMS, max_frames=40)
    assert not np.array_equal(other.controls, run.controls[:40])


def test_local_maps_are_fused_with_vo_poses(short_run) -> None:
    """Heights in the maps: sand is flat, so most informative cells have a small spread."""
    run, _, _ = short_run
    n, sz, szz = np.moveaxis(run.local_maps, -1, 0)
    ok = n >= 3
    std = np.sqrt(np.maximum(szz[ok] / n[ok] - (sz[ok] / n[ok]) ** 2, 0))
    assert np.median(std) < 0.08
    assert np.percentile(std, 99) > 0.2  # rocks, poles, bins stand out


def test_unknown_course_is_named() -> None:
    with pytest.raises(ArgumentError, match="course must be one of mars-yard-a, .*got 'mars-yard'"):
        simulate_run("mars-yard", 0, PARAMS)


def test_noise_seed_drives_the_same_terrain_again(short_run) -> None:
    """noise_seed changes the VO and sensor noise only: the same ground truth through the same
    world, other controls and local maps; the default is the simulation seed's own noise."""
    run, info, _ = short_run
    again, info2 = simulate_run("mars-yard-a", seed=2, params=PARAMS, max_frames=120,
                                noise_seed=7)
    np.testing.assert_array_equal(again.ground_truth, run.ground_truth)
    assert info2.world.fingerprint() == info.world.fingerprint()
    assert not np.allclose(again.controls, run.controls)
    same, _ = simulate_run("mars-yard-a", seed=2, params=PARAMS, max_frames=120, noise_seed=2)
    np.testing.assert_array_equal(same.controls, run.controls)
    np.testing.assert_array_equal(same.local_maps, run.local_maps)
