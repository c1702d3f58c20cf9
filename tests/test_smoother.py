"""The particle smoother's mean path (``rbpf.smoothed_mean_path``) against a plain loop over
the ancestry, and the reported trajectory ([filter] estimate) of a run."""

import jax.numpy as jnp
import numpy as np
import pytest
from synthetic import make_run

from gslam_jax import rbpf, slam
from gslam_jax.config import apply_overrides, Config


def _loop_smoother(poses, ancestors, log_w):
    """Walk each final particle's lineage back frame by frame; weight by the final weights."""
    T, J, _ = poses.shape
    w = np.exp(log_w - log_w.max())
    w /= w.sum()
    out = np.zeros((T, 3))
    for t in range(T):
        xs, ys, ss, cs = 0.0, 0.0, 0.0, 0.0
        for j in range(J):
            slot = j
            for u in range(T - 1, t, -1):  # slot at frame u -> its parent's slot at frame u - 1
                slot = ancestors[u, slot]
            p = poses[t, slot]
            xs, ys = xs + w[j] * p[0], ys + w[j] * p[1]
            ss, cs = ss + w[j] * np.sin(p[2]), cs + w[j] * np.cos(p[2])
        out[t] = xs, ys, np.arctan2(ss, cs)
    return out


def test_smoothed_mean_path_matches_a_loop_over_the_ancestry():
    rng = np.random.default_rng(0)
    T, J = 7, 5
    poses = rng.normal(size=(T, J, 3))
    poses[..., 2] = rng.uniform(-np.pi, np.pi, size=(T, J))
    ancestors = rng.integers(0, J, size=(T, J))
    log_w = rng.normal(size=J)
    got = rbpf.smoothed_mean_path(jnp.asarray(poses), jnp.asarray(ancestors), jnp.asarray(log_w))
    want = _loop_smoother(poses, ancestors, log_w)
    np.testing.assert_allclose(np.asarray(got)[:, :2], want[:, :2], atol=1e-5)
    d = np.angle(np.exp(1j * (np.asarray(got)[:, 2] - want[:, 2])))
    np.testing.assert_allclose(d, 0.0, atol=1e-5)


def test_one_surviving_lineage_is_the_best_path():
    """When every final particle descends from one ancestor, the smoother's mean is that path."""
    T, J = 6, 4
    poses = np.random.default_rng(1).normal(size=(T, J, 3))
    ancestors = np.zeros((T, J), int)  # every slot's parent is slot 0
    got = np.asarray(rbpf.smoothed_mean_path(jnp.asarray(poses), jnp.asarray(ancestors),
                                             jnp.zeros(J)))
    np.testing.assert_allclose(got[:-1], poses[:-1, 0], atol=1e-6)


@pytest.mark.parametrize("estimate", ["best", "mean", "smoothed"])
def test_each_estimate_ends_where_its_definition_says(estimate):
    """At the final frame the best particle's path is at the best particle, and the smoother's
    mean is the filtering mean (both are averages of the same final particles); the reported
    path is the configured one."""
    run, _ = make_run(steps=20)
    cfg = apply_overrides(Config(), ["filter.particles=8", f"filter.estimate={estimate}"])
    res = slam.run_slam(run, cfg)
    np.testing.assert_allclose(res.best_path[-1], res.best_pose[-1], atol=1e-6)
    np.testing.assert_allclose(res.smoothed_path[-1], res.mean_pose[-1], atol=1e-5)
    want = {"best": res.best_path, "mean": res.mean_pose, "smoothed": res.smoothed_path}
    np.testing.assert_array_equal(res.path, want[estimate])
