"""The particle smoother's mean path (``rbpf.smoothed_mean_path``) and mean-step path
(``rbpf.smoothed_step_path``) against plain loops over the ancestry, and the reported
trajectory ([filter] estimate) of a run."""

import jax.numpy as jnp
import numpy as np
import pytest
from synthetic import make_run

from gslam_jax import rbpf
from gslam_jax.config import apply_overrides, Config
from gslam_jax.driver import slam


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


def _random_ancestry(seed: int, T: int = 7, J: int = 5):
    """Poses [T, J, 3] (any heading), ancestors [T, J] and final log weights [J] at random."""
    rng = np.random.default_rng(seed)
    poses = rng.normal(size=(T, J, 3))
    poses[..., 2] = rng.uniform(-np.pi, np.pi, size=(T, J))
    return poses, rng.integers(0, J, size=(T, J)), rng.normal(size=J)


def test_smoothed_mean_path_matches_a_loop_over_the_ancestry():
    poses, ancestors, log_w = _random_ancestry(0)
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


def _loop_step_path(poses, ancestors, log_w):
    """Each final particle's whole path by walking its lineage back, its steps in the frame of
    each step's start, the steps' weighted mean per frame composed from the weighted start."""
    T, J, _ = poses.shape
    w = np.exp(log_w - log_w.max())
    w /= w.sum()
    lineages = np.zeros((J, T, 3))
    for j in range(J):
        slot = j
        for t in range(T - 1, -1, -1):
            lineages[j, t] = poses[t, slot]
            slot = ancestors[t, slot]
    start = lineages[:, 0]
    out = [np.array([w @ start[:, 0], w @ start[:, 1],
                     np.arctan2(w @ np.sin(start[:, 2]), w @ np.cos(start[:, 2]))])]
    for t in range(1, T):
        a, b = lineages[:, t - 1], lineages[:, t]
        c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
        dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
        step = w @ np.stack([c * dx + s * dy, -s * dx + c * dy,
                             np.angle(np.exp(1j * (b[:, 2] - a[:, 2])))], -1)
        p = out[-1]
        out.append(p + np.array([np.cos(p[2]) * step[0] - np.sin(p[2]) * step[1],
                                 np.sin(p[2]) * step[0] + np.cos(p[2]) * step[1], step[2]]))
    return np.array(out)


def test_smoothed_step_path_matches_a_loop_over_the_ancestry():
    poses, ancestors, log_w = _random_ancestry(2)
    got = rbpf.smoothed_step_path(jnp.asarray(poses), jnp.asarray(ancestors), jnp.asarray(log_w))
    np.testing.assert_allclose(np.asarray(got), _loop_step_path(poses, ancestors, log_w),
                               atol=1e-4)


def test_spread_headings_shorten_the_mean_path_and_not_the_mean_steps():
    """Particles that leave one start along straight lines at headings +-0.3 rad (no
    resampling), equal weights: each walks 1 m a frame. Their mean position moves cos 0.3 m a
    frame, their mean step 1 m."""
    T, J = 11, 2
    heading = np.array([0.3, -0.3])
    d = np.arange(T)[:, None]
    poses = np.stack([d * np.cos(heading), d * np.sin(heading),
                      np.broadcast_to(heading, (T, J))], -1)
    ancestors = np.broadcast_to(np.arange(J), (T, J))
    args = jnp.asarray(poses), jnp.asarray(ancestors), jnp.zeros(J)
    mean = np.asarray(rbpf.smoothed_mean_path(*args))
    steps = np.asarray(rbpf.smoothed_step_path(*args))
    np.testing.assert_allclose(mean[-1, :2], [(T - 1) * np.cos(0.3), 0.0], atol=1e-5)
    np.testing.assert_allclose(steps[:, :2], np.stack([np.arange(T), np.zeros(T)], -1),
                               atol=1e-5)


@pytest.mark.parametrize("estimate", ["best", "mean", "smoothed", "steps", "mode",
                                      "local_steps"])
def test_each_estimate_ends_where_its_definition_says(estimate):
    """At the final frame the best particle's path is at the best particle, and the smoother's
    mean is the filtering mean (both are averages of the same final particles); the reported
    path is the configured one."""
    run, _ = make_run(steps=20)
    cfg = apply_overrides(Config(), ["filter.particles=8", f"filter.estimate={estimate}"])
    res = slam.run_slam(run, cfg)
    np.testing.assert_allclose(res.best_path[-1], res.best_pose[-1], atol=1e-6)
    np.testing.assert_allclose(res.smoothed_path[-1], res.mean_pose[-1], atol=1e-5)
    np.testing.assert_allclose(res.steps_path[0], res.smoothed_path[0], atol=1e-5)
    want = {"best": res.best_path, "mean": res.mean_pose, "smoothed": res.smoothed_path,
            "steps": res.steps_path, "mode": res.mode_path, "local_steps": res.local_steps_path}
    np.testing.assert_array_equal(res.path, want[estimate])
