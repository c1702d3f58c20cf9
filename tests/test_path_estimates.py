"""``results.PathEstimates``: the trajectories through the particles' ancestry are built when
first read, once each, and turned into the run's frame; given paths are kept as given."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

from gslam_jax import rbpf
from gslam_jax.driver.results import ANCESTRY_PATHS, Ancestry, PathEstimates, SlamResult

T, J = 6, 5


def _ancestry(heading: float = 0.0) -> Ancestry:
    rng = np.random.default_rng(0)
    pose = rng.normal(size=(T, J, 3)).astype(np.float32)
    ancestors = rng.integers(0, J, size=(T, J)).astype(np.int32)
    log_w = jnp.asarray(np.log(np.full(J, 1.0 / J, np.float32)))
    return Ancestry(pose=pose, ancestors=ancestors, log_w=log_w, best=jnp.int32(2),
                    map_slot=jnp.int32(4), step_log_w=np.zeros((T, J), np.float32),
                    resampled=np.zeros(T, bool), mean_pose=pose.mean(axis=1), run=None,
                    heading=heading)


def _counting(monkeypatch, name: str) -> list:
    calls = []
    real = getattr(rbpf, name)

    def counted(*args, **kwargs):
        calls.append(args)
        return real(*args, **kwargs)

    monkeypatch.setattr(rbpf, name, counted)
    return calls


def test_a_path_is_built_on_first_read_and_once(monkeypatch):
    backtrack = _counting(monkeypatch, "backtrack_path")
    smoothed = _counting(monkeypatch, "smoothed_mean_path")
    paths = PathEstimates(_ancestry())
    assert not backtrack and not smoothed  # nothing built with the result
    best = paths["best"]
    assert len(backtrack) == 1 and not smoothed
    assert paths["best"] is best and len(backtrack) == 1  # kept
    # the best particle's ancestry, followed by hand
    a = _ancestry()
    slot, want = 2, np.zeros((T, 3))
    for t in range(T - 1, -1, -1):
        want[t] = a.pose[t, slot]
        slot = a.ancestors[t, slot]
    np.testing.assert_allclose(best, want, atol=1e-6)
    paths["map"]
    assert len(backtrack) == 2 and not smoothed


def test_both_mode_paths_find_the_densest_particle_once(monkeypatch):
    densest = _counting(monkeypatch, "densest_particle")
    paths = PathEstimates(_ancestry())
    paths["mode"], paths["mode_mean"]
    assert len(densest) == 1


def test_paths_are_turned_into_the_runs_frame():
    heading = math.radians(30.0)
    on_axes, turned = PathEstimates(_ancestry()), PathEstimates(_ancestry(heading))
    p, q = on_axes["best"], turned["best"]
    c, s = math.cos(heading), math.sin(heading)
    np.testing.assert_allclose(q[:, 0], c * p[:, 0] - s * p[:, 1], atol=1e-5)
    np.testing.assert_allclose(q[:, 1], s * p[:, 0] + c * p[:, 1], atol=1e-5)
    np.testing.assert_allclose(q[:, 2], p[:, 2] + heading, atol=1e-5)


def test_given_paths_are_kept_and_the_others_are_none():
    vo = np.arange(12.0).reshape(4, 3)
    paths = PathEstimates.given(best=vo, map=vo)
    assert paths["best"] is vo and paths["map"] is vo
    assert all(paths[name] is None for name in ANCESTRY_PATHS if name not in ("best", "map"))
    with pytest.raises(KeyError, match="no path estimate 'nearest'"):
        paths["nearest"]
    with pytest.raises(ValueError, match="unknown path estimates"):
        PathEstimates.given(nearest=vo)


def test_the_result_reports_the_configured_estimate():
    vo, mean = np.zeros((4, 3)), np.ones((4, 3))
    fields = dict(best_pose=vo, mean_pose=mean, vo_path=vo, ess=np.ones(4),
                  resampled=np.zeros(4, bool), updated=np.ones(4, bool), log_lik=np.zeros(4),
                  exponent=np.ones(4), kmap=np.ones((2, 2)), smap=np.ones((2, 2)),
                  map_origin=(0.0, 0.0), resolution=0.1, extent_violations=0,
                  empty_observations=0, seconds=0.0, compile_seconds=0.0)
    paths = PathEstimates.given(best=vo + 2, smoothed=vo + 3)
    assert (SlamResult(paths, **fields).path == 2).all()
    assert (SlamResult(paths, **fields, estimate="mean").path == 1).all()
    assert (SlamResult(paths, **fields, estimate="smoothed").smoothed_path == 3).all()
