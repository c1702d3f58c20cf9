"""rbpf.local_step_path and rbpf.factor_cover (``[filter] estimate = "local_steps"``) against
loops over frames, particles and lineages, and the limit where they are the steps estimate."""

import math

import jax.numpy as jnp
import numpy as np

from gslam_jax.driver.observations import local_map_footprints
from gslam_jax.rbpf.paths import (COVER_SPREADS, StepHistory, factor_cover, local_step_path,
                                  smoothed_step_path)
from gslam_jax.vo.localmap import LocalMapParams
from tests.synthetic import make_run


def _walk(T, J, rng):
    """Random-walk poses [T, J, 3] of J particles."""
    poses = np.zeros((T, J, 3))
    for t in range(1, T):
        fwd, side = 1.0 + 0.1 * rng.standard_normal(J), 0.05 * rng.standard_normal(J)
        th = poses[t - 1, :, 2]
        poses[t, :, 0] = poses[t - 1, :, 0] + fwd * np.cos(th) - side * np.sin(th)
        poses[t, :, 1] = poses[t - 1, :, 1] + fwd * np.sin(th) + side * np.cos(th)
        poses[t, :, 2] = th + 0.1 * rng.standard_normal(J)
    return poses


def _history(log_w, resampled, T):
    return StepHistory(jnp.asarray(log_w), jnp.asarray(resampled), jnp.zeros((T, 3)),
                       jnp.full((T, 3), -1.0))


def _by_hand(poses, ancestors, log_w, resampled, first):
    """For each step t, every final particle's lineage, weighed by the change of its log
    weights at each frame u after the last resampling whose cover [first[u], u] holds t."""
    T, J, _ = poses.shape
    lineage = np.zeros((T, J), int)
    lineage[-1] = np.arange(J)
    for t in range(T - 1, 0, -1):
        lineage[t - 1] = ancestors[t][lineage[t]]
    last = max([u for u in range(T) if resampled[u]], default=0)

    def weights(t):
        lw = np.zeros(J)
        for u in range(last + 1, T):
            if first[u] <= t <= u:
                lw += log_w[u] - log_w[u - 1]
        w = np.exp(lw - lw.max())
        return w / w.sum()

    steps = []
    for t in range(1, T):
        w, mean = weights(t), np.zeros(3)
        for j in range(J):
            a, b = poses[t - 1, lineage[t - 1, j]], poses[t, lineage[t, j]]
            dx, dy = b[:2] - a[:2]
            mean += w[j] * np.array([math.cos(a[2]) * dx + math.sin(a[2]) * dy,
                                     -math.sin(a[2]) * dx + math.cos(a[2]) * dy, b[2] - a[2]])
        steps.append(mean)
    w1 = weights(1)
    p0 = poses[0, lineage[0]]
    path = [np.array([w1 @ p0[:, 0], w1 @ p0[:, 1],
                      math.atan2(w1 @ np.sin(p0[:, 2]), w1 @ np.cos(p0[:, 2]))])]
    for m in steps:
        p = path[-1]
        path.append(p + np.array([m[0] * math.cos(p[2]) - m[1] * math.sin(p[2]),
                                  m[0] * math.sin(p[2]) + m[1] * math.cos(p[2]), m[2]]))
    return np.array(path)


def _case(seed, T=10, J=6, resample_at=()):
    rng = np.random.default_rng(seed)
    poses = _walk(T, J, rng)
    ancestors = np.tile(np.arange(J), (T, 1))
    resampled = np.zeros(T, bool)
    log_w = np.zeros((T, J))
    log_w[0] = -np.log(J)
    for t in range(1, T):
        if t in resample_at:
            ancestors[t] = rng.integers(0, J, J)
            resampled[t] = True
            log_w[t] = -np.log(J)
            continue
        lw = log_w[t - 1] + rng.standard_normal(J)
        log_w[t] = lw - np.log(np.exp(lw).sum())
    first = np.array([rng.integers(1, u + 2) for u in range(T)])  # covers first[u] .. u
    return poses, ancestors, log_w, resampled, first


def test_each_step_weighed_by_the_factors_that_cover_it():
    for seed, resample_at in ((0, ()), (1, (4,)), (2, (3, 7))):
        poses, ancestors, log_w, resampled, first = _case(seed, resample_at=resample_at)
        got = local_step_path(jnp.asarray(poses), jnp.asarray(ancestors),
                              _history(log_w, resampled, len(poses)), jnp.asarray(first))
        want = _by_hand(poses, ancestors, log_w, resampled, first)
        np.testing.assert_allclose(np.asarray(got), want, atol=3e-5)


def test_factors_covering_every_earlier_step_give_the_steps_estimate():
    # one factor, at the last frame, covering every step: the final weights on every step
    poses, ancestors, log_w, resampled, _ = _case(3, resample_at=(2, 5))
    T, J, _ = poses.shape
    log_w[6:-1] = -np.log(J)
    first = np.arange(T) + 1
    first[-1] = 1
    got = local_step_path(jnp.asarray(poses), jnp.asarray(ancestors),
                          _history(log_w, resampled, T), jnp.asarray(first))
    want = smoothed_step_path(jnp.asarray(poses), jnp.asarray(ancestors),
                              jnp.asarray(log_w[-1]))
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=3e-5)


def _cover_by_hand(poses, log_w, mean, footprint):
    T = len(poses)
    w = np.exp(log_w) / np.exp(log_w).sum(axis=1, keepdims=True)
    spread = np.sqrt((w * ((poses[..., :2] - mean[:, None, :2]) ** 2).sum(-1)).sum(-1))
    centre = np.array([mean[t, :2] + [math.cos(mean[t, 2]) * footprint[t, 0]
                                      - math.sin(mean[t, 2]) * footprint[t, 1],
                                      math.sin(mean[t, 2]) * footprint[t, 0]
                                      + math.cos(mean[t, 2]) * footprint[t, 1]]
                       for t in range(T)])
    first = []
    for u in range(T):
        older = [s for s in range(u) if footprint[s, 2] >= 0 and footprint[u, 2] >= 0
                 and np.linalg.norm(centre[s] - centre[u])
                 <= footprint[s, 2] + footprint[u, 2]
                 + COVER_SPREADS * math.sqrt(abs(spread[u] ** 2 - spread[s] ** 2))]
        first.append(min(older) + 1 if older else u + 1)
    return np.array(first)


def test_cover_reaches_back_to_the_oldest_overlapping_map_and_over_a_loop():
    # a 40-frame square loop of 1 m steps; footprints 3 m ahead of the robot, radius 2 m,
    # every other frame; the particles spread about the mean as they go
    rng = np.random.default_rng(4)
    T, J = 40, 8
    heading = np.repeat(np.arange(4) * math.pi / 2, 10)
    xy = np.cumsum(np.stack([np.cos(heading), np.sin(heading)], axis=1), axis=0)
    mean = np.concatenate([xy - xy[0], heading[:, None]], axis=1)
    poses = mean[:, None, :] + (np.linspace(0, 0.3, T)[:, None, None]
                                * rng.standard_normal((T, J, 3)))
    log_w = np.log(np.full((T, J), 1.0 / J))
    footprint = np.tile([3.0, 0.0, 2.0], (T, 1))
    footprint[1::2, 2] = -1.0
    history = StepHistory(jnp.asarray(log_w), jnp.zeros(T, bool), jnp.asarray(mean),
                          jnp.asarray(footprint))
    got = np.asarray(factor_cover(jnp.asarray(poses), history))
    want = _cover_by_hand(poses, log_w, mean, footprint)
    np.testing.assert_array_equal(got, want)
    assert (got[1::2] == np.arange(1, T, 2) + 1).all()     # no local map: covers nothing
    assert 0 < want[10] - 1 < 10                             # a neighbour's map, not all
    assert got[38] == 1                                     # back at the start: the loop


def test_footprints_hold_every_observed_cell():
    # a circle, its local maps on the map's lattice (turned against the robot's)
    run, _ = make_run(steps=30, params=LocalMapParams(resolution=0.16, max_range=5.0,
                                                      travel=1.0, lattice="map"))
    assert np.ptp(run.lattice_heading_array()) > 0.5
    fp = local_map_footprints(run)
    L, res = run.local_maps.shape[1], run.resolution
    for t in range(run.num_frames):
        m = run.obs_index[t]
        if m < 0:
            assert fp[t, 2] == -1.0
            continue
        i, j = np.nonzero(run.local_maps[m, :, :, 0] > 0)
        a = run.lattice_heading_array()[m]
        x, y = (i - L // 2 + 0.5) * res, (j - L // 2 + 0.5) * res
        px, py = math.cos(a) * x - math.sin(a) * y, math.sin(a) * x + math.cos(a) * y
        d = np.hypot(px - fp[t, 0], py - fp[t, 1])
        assert d.max() <= fp[t, 2] and fp[t, 2] - d.max() < res
