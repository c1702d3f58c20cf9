"""experiments/pose_objective.py: the score of a local map over poses around the truth, with
the map built at the true poses, peaks at the truth on exact data and moves with the truth."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from synthetic import World, truth_and_controls

from experiments import pose_objective as P
from gslam_jax import rbpf
from gslam_jax.config import Config
from gslam_jax.driver import observations
from gslam_jax.rbpf.motion import MotionParams
from gslam_jax.run import Run, integrate_controls
from gslam_jax.vo.localmap import LocalMapParams, build_local_maps

GRID = P.offset_grid(0.4, 0.08, 0.03, 0.01)  # 11 x 11 x 7 offsets


@pytest.fixture(scope="module")
def run() -> Run:
    """A loop with exact odometry through a rough world (many small bumps: structure at the
    scale of a few cells, so that the score can locate the robot to a cell)."""
    world = World(0, half_size=10.0, n_bumps=100)
    world.radii = np.random.default_rng(7).uniform(0.1, 0.4, 100)
    rng = np.random.default_rng(1)
    steps = 30
    gt, u = truth_and_controls("loop", steps)
    params = LocalMapParams(resolution=0.16, max_range=5.0, travel=1.0)
    obs_index, maps, *_ = build_local_maps(integrate_controls(u), [world.observe(p, rng)
                                                                   for p in gt], params)
    return Run(controls=u, obs_index=obs_index, local_maps=maps, resolution=0.16,
               timestamps=np.arange(steps) * 0.2, ground_truth=gt,
               vo_failed=np.zeros(steps, bool), initial_pose=np.zeros(3))


def test_grid_is_symmetric_and_holds_the_truth():
    g = P.offset_grid(0.5, 0.04, 0.05, 0.005)
    assert [len(a) for a in g] == [25, 25, 21]
    for a in g:
        assert a[len(a) // 2] == 0.0 and np.allclose(a, -a[::-1])
    np.testing.assert_allclose(g.steps, [0.04, 0.04, 0.005])


def test_peak_and_information_of_a_known_quadratic():
    """A quadratic score centred on a grid point: the peak is that point, in (along, across,
    heading) order, and both the second difference and the fitted parabola give 1 / sigma^2."""
    centre = np.array([0.16, -0.24, 0.01])
    sigma = np.array([0.2, 0.1, 0.02])
    off = np.stack(np.meshgrid(*GRID, indexing="ij"), -1)
    scores = -0.5 * np.sum(((off - centre) / sigma) ** 2, -1)
    index, offset = P.peak(scores, GRID)
    np.testing.assert_allclose(offset, centre, atol=1e-12)
    edge = P.peak(scores + 10.0 * off[..., 0], GRID)[0]
    assert edge[0] == len(GRID.along) - 1  # an along-track slope puts the peak on that edge
    np.testing.assert_allclose(P.information(scores, index, GRID), sigma ** -2.0, rtol=1e-9)
    np.testing.assert_allclose(P.fitted_information(scores, GRID), sigma ** -2.0, rtol=1e-9)


def test_ties_go_to_the_offset_nearest_the_truth():
    scores = np.zeros([len(a) for a in GRID])
    scores[1:, 1:, :] = 1.0  # a plateau holding the truth and points away from it
    assert np.all(P.peak(scores, GRID)[1] == 0.0)


def test_prior_variances_of_a_straight_drive_in_the_robot_frame():
    """Along-track and heading variance n steps of d metres after an update frame:
    n (alpha_d d)^2 and n (alpha_theta_d d)^2; the same whatever the heading."""
    params = rbpf.FilterParams(motion=MotionParams(0.05, 0.01, 0.05))
    d, T = 0.5, 7
    u = np.tile([d, 0.0, 0.0], (T, 1))
    obs_index = np.array([0, -1, -1, 1, -1, -1, -1])
    for heading in (0.0, 1.2):
        start = np.array([1.0, 2.0, heading])
        truth = integrate_controls(u, start)
        var = P.prior_variances(u, obs_index, start, truth, params)
        n = np.array([1, 1, 2, 3, 1, 2, 3])  # steps since the last update frame, this one's too
        np.testing.assert_allclose(var[:, 0], n * (0.05 * d) ** 2, rtol=1e-5)
        np.testing.assert_allclose(var[:, 2], n * (0.01 * d) ** 2, rtol=1e-5)
        # across-track only through the heading noise of earlier steps
        assert var[1, 1] == pytest.approx(0.0, abs=1e-9)
        assert var[3, 1] > var[2, 1] > 0


def _self_map(run: Run, config: Config, t: int):
    """One particle whose map holds only the local map of frame ``t``, at its true pose."""
    cfg, params = P.truth_config(run, config)
    obs = observations.map_observations(run, config)[int(run.obs_index[t])]
    pose = jnp.asarray(run.ground_truth[t], jnp.float32)
    u = rbpf.update_noise(jax.random.key(0), cfg).unknown_u
    state, _ = P._update(rbpf.init(cfg)._replace(pose=pose[None]), obs, u, params, cfg)
    return state, obs, u, params, cfg


@pytest.mark.parametrize("shift,expected", [((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
                                            ((0.16, -0.08, 0.0), (-0.16, 0.08, 0.0)),
                                            ((0.0, 0.0, 0.02), (0.0, 0.0, -0.02))])
def test_a_local_map_against_itself_peaks_where_it_was_written(run, shift, expected):
    """Scored against a map of itself alone, a local map peaks exactly at the pose it was
    written from: at zero offset around that pose, and at minus the shift around a shifted
    centre (along, across and heading each)."""
    t = int(np.flatnonzero(run.obs_index >= 0)[6])
    state, obs, u, params, cfg = _self_map(run, Config(), t)
    centre = P.compose(run.ground_truth[t], np.asarray(shift))
    scores, overlap = P.score_grid(state.maps, jnp.asarray(centre, jnp.float32), obs, u,
                                   *[jnp.asarray(a, jnp.float32) for a in GRID], params, cfg)
    assert int(overlap) > 100
    np.testing.assert_allclose(P.peak(np.asarray(scores, np.float64), GRID)[1], expected,
                               atol=1e-9)


def test_peak_at_the_truth_on_exact_odometry_and_moves_with_it(run):
    """Maps at the true poses: most updates peak within one cell and 0.01 rad of the truth;
    with the grid centred 0.24 m ahead of the truth, the peaks move 0.24 m back."""
    scores = P.pose_objective(run, Config(), GRID)
    assert len(scores) == int(np.sum(run.obs_index >= 0))
    assert not scores[0].scored  # the first local map has no map to be scored against
    summary = P.summary(scores, run.resolution)
    assert summary["scored"] == len(scores) - 1
    assert summary["within"] >= 0.75, summary
    moved = P.summary(P.pose_objective(run, Config(), GRID, np.array([0.24, 0.0, 0.0])),
                      run.resolution)
    assert moved["within"] <= 0.25, moved
    assert moved["median_abs_peak_along"] == pytest.approx(0.24, abs=0.081), moved
    assert moved["mean_peak_along"] < -0.16, moved
