"""The ``mode`` and ``mode_mean`` estimates: ``rbpf.densest_particle`` against a brute-force
count over every pair, the paths they report against following the ancestry by hand, and the
map a run reports with them: the local maps placed along the mode's path (NumPy's
``pose_maps.pose_map``)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from cached_runs import FRAMES, shared_run

from gslam_jax import choices, rbpf
from gslam_jax.config import Config, apply_overrides
from gslam_jax.driver import slam
from gslam_jax.gridmap.pose_maps import pose_map
from gslam_jax.rbpf.paths import MODE_RADIUS_M


def _brute_force(pose: np.ndarray, log_w: np.ndarray, radius: float) -> int:
    w = np.exp(log_w - log_w.max())
    w = w / w.sum()
    mass = [sum(w[i] for i in range(len(w))
                if np.hypot(*(pose[i, :2] - pose[j, :2])) <= radius) for j in range(len(w))]
    mass = np.asarray(mass)
    top = np.flatnonzero(mass >= mass.max() - 1e-6)
    return int(top[np.argmax(w[top])])


@pytest.mark.parametrize("seed", range(6))
def test_densest_particle_matches_a_count_over_every_pair(seed):
    """Clouds of 2-4 clusters of random size and spread (some with duplicated particles, as
    after a resampling), random weights; J = 300, more than one block of rows."""
    rng = np.random.default_rng(seed)
    J = 300
    centres = rng.uniform(-20, 20, (rng.integers(2, 5), 2))
    which = rng.integers(0, len(centres), J)
    xy = centres[which] + rng.normal(0, rng.uniform(0.2, 2.0), (J, 2))
    if seed % 2:  # duplicated particles, as after a resampling
        xy[::7] = xy[1::7]
    pose = np.concatenate([xy, rng.uniform(-np.pi, np.pi, (J, 1))], 1).astype(np.float32)
    log_w = rng.normal(0, 1.0, J).astype(np.float32)
    got = int(rbpf.densest_particle(jnp.asarray(pose), jnp.asarray(log_w)))
    assert got == _brute_force(pose, log_w, MODE_RADIUS_M)


def test_the_mode_is_the_cluster_not_the_single_heaviest_particle():
    """One particle 10 m off with 30 % of the weight, 70 near the origin sharing the rest: the
    best particle is the lone one, the densest is the near one of highest weight."""
    rng = np.random.default_rng(0)
    xy = np.concatenate([[[10.0, 0.0]], rng.normal(0, 0.2, (70, 2))])
    pose = np.concatenate([xy, np.zeros((71, 1))], 1).astype(np.float32)
    w = np.concatenate([[0.3], np.full(70, 0.01)])
    w[5] = 0.0101
    log_w = np.log(w / w.sum()).astype(np.float32)
    assert int(np.argmax(log_w)) == 0
    assert int(rbpf.densest_particle(jnp.asarray(pose), jnp.asarray(log_w))) == 5


def test_mode_path_follows_the_densest_particles_ancestry():
    """``ancestry_path("mode")`` is the densest final particle's ancestral path, traced by hand
    through a random ancestry."""
    rng = np.random.default_rng(3)
    T, J = 12, 40
    poses = rng.normal(0, 3.0, (T, J, 3)).astype(np.float32)
    ancestors = rng.integers(0, J, (T, J)).astype(np.int32)
    log_w = rng.normal(0, 1.0, J).astype(np.float32)
    path = np.asarray(rbpf.ancestry_path("mode", jnp.asarray(poses), jnp.asarray(ancestors),
                                         jnp.asarray(log_w), jnp.int32(0)))
    j = _brute_force(poses[-1], log_w, MODE_RADIUS_M)
    want = np.empty((T, 3), np.float32)
    for t in range(T - 1, -1, -1):
        want[t] = poses[t, j]
        j = ancestors[t, j]
    np.testing.assert_array_equal(path, want)


def _ancestral_paths(poses: np.ndarray, ancestors: np.ndarray) -> np.ndarray:
    """Every final particle's path through the ancestry, by hand: [T, J, 3] -> [J, T, 3]."""
    T, J, _ = poses.shape
    out = np.empty((J, T, 3), np.float64)
    for j0 in range(J):
        j = j0
        for t in range(T - 1, -1, -1):
            out[j0, t] = poses[t, j]
            j = ancestors[t, j]
    return out


@pytest.mark.parametrize("seed", range(4))
def test_mode_mean_path_is_the_weighted_mean_of_the_modes_neighbours_paths(seed):
    """``ancestry_path("mode_mean")``: the final particles within 1 m of the brute-force
    densest one, each one's ancestral path traced by hand, averaged with their final weights
    renormalised (headings by circular mean). Two clusters 6 m apart at the end, the
    heavier in total weight not holding the heaviest particle."""
    rng = np.random.default_rng(seed)
    T, J = 10, 48
    poses = rng.normal(0, 2.0, (T, J, 3))
    poses[-1, :, :2] = rng.normal(0, 0.3, (J, 2))
    poses[-1, :12, 0] += 6.0  # a second cluster
    ancestors = rng.integers(0, J, (T, J)).astype(np.int32)
    log_w = rng.normal(0, 0.5, J)
    log_w[0] = 2.5  # the heaviest particle, in the lighter cluster
    poses, log_w = poses.astype(np.float32), log_w.astype(np.float32)
    got = np.asarray(rbpf.ancestry_path("mode_mean", jnp.asarray(poses),
                                        jnp.asarray(ancestors), jnp.asarray(log_w),
                                        jnp.int32(0)))
    centre = poses[-1, _brute_force(poses[-1], log_w, MODE_RADIUS_M), :2]
    near = np.hypot(*(poses[-1, :, :2] - centre).T) <= MODE_RADIUS_M
    assert 1 < near.sum() < J and not near[0]
    w = np.exp(log_w.astype(np.float64)) * near
    w /= w.sum()
    paths = _ancestral_paths(poses, ancestors)
    want_xy = np.einsum("j,jta->ta", w, paths[:, :, :2])
    want_th = np.arctan2(w @ np.sin(paths[:, :, 2]), w @ np.cos(paths[:, :, 2]))
    np.testing.assert_allclose(got[:, :2], want_xy, atol=1e-4)
    np.testing.assert_allclose(np.angle(np.exp(1j * (got[:, 2] - want_th))), 0.0, atol=1e-4)


def test_mode_mean_path_of_a_lone_mode_is_its_path_and_of_one_cluster_the_smoothed_path():
    """With every final particle within 1 m of each other the mode's component is the whole
    cloud (the smoother's mean path); with one particle holding nearly all the weight far from
    the rest it is that particle's ancestral path."""
    rng = np.random.default_rng(11)
    T, J = 8, 20
    poses = rng.normal(0, 2.0, (T, J, 3)).astype(np.float32)
    poses[-1, :, :2] = rng.normal(0, 0.05, (J, 2))
    ancestors = rng.integers(0, J, (T, J)).astype(np.int32)
    log_w = rng.normal(0, 0.5, J).astype(np.float32)
    args = jnp.asarray(poses), jnp.asarray(ancestors), jnp.asarray(log_w)
    np.testing.assert_allclose(np.asarray(rbpf.mode_mean_path(*args)),
                               np.asarray(rbpf.smoothed_mean_path(*args)), atol=1e-6)
    poses[-1, 3, :2] = 30.0
    log_w[3] = 20.0
    args = jnp.asarray(poses), jnp.asarray(ancestors), jnp.asarray(log_w)
    got, want = np.asarray(rbpf.mode_mean_path(*args)), _ancestral_paths(poses, ancestors)[3]
    np.testing.assert_allclose(got[:, :2], want[:, :2], atol=1e-5)
    # a circular mean gives the heading in (-pi, pi]
    np.testing.assert_allclose(np.angle(np.exp(1j * (got[:, 2] - want[:, 2]))), 0.0, atol=1e-5)


@pytest.mark.parametrize("estimate", choices.ESTIMATES)
def test_the_map_goes_with_the_mode_and_otherwise_with_the_best_particle(estimate):
    """``map_particle``: the densest particle under "mode" and "mode_mean" (the brute-force
    count), the best slot under every other estimate, here a slot that is not the densest."""
    rng = np.random.default_rng(7)
    pose = np.concatenate([rng.normal(0, 0.3, (30, 2)), np.zeros((30, 1))], 1)
    pose[0, :2] = 9.0
    log_w = rng.normal(0, 0.1, 30)
    log_w[0] = 3.0  # the heaviest particle stands alone
    pose, log_w = pose.astype(np.float32), log_w.astype(np.float32)
    densest = _brute_force(pose, log_w, MODE_RADIUS_M)
    assert densest != 0
    got = int(rbpf.map_particle(estimate, jnp.asarray(pose), jnp.asarray(log_w), jnp.int32(0)))
    assert got == (densest if estimate in ("mode", "mode_mean") else 0)


@pytest.mark.slow
def test_a_mode_run_reports_the_map_laid_along_the_modes_path():
    """``run_slam`` with ``estimate = "mode"`` on a run whose final densest and best particles
    differ: ``map_path`` is the mode's path, and the local maps placed along it (NumPy, eq.
    14's sums) give the reported map's counts in every cell, which the best particle's path
    does not."""
    run = shared_run(FRAMES)
    config = apply_overrides(Config(), ["filter.particles=16", "filter.seed=3",
                                        "filter.estimate=mode", "map.margin=1.0"])
    res = slam.run_slam(run, config)
    assert np.abs(res.mode_path - res.best_path).max() > 0.05  # the case this test is about
    np.testing.assert_array_equal(res.map_path, res.mode_path)
    np.testing.assert_array_equal(pose_map(run, res.map_path, lattice=res.grid).k, res.kmap)
    assert (pose_map(run, res.best_path, lattice=res.grid).k != res.kmap).any()
