"""experiments.revisit_weights: pose errors in the true robot frame and the per-window figures,
on hand-made particle clouds (no filter run)."""

from __future__ import annotations

import math

import numpy as np

from experiments.revisit_weights import pose_errors, window_rows
from gslam_jax.evaluation import loops
from gslam_jax.gridmap.grid import arc_length


def test_pose_errors_in_the_true_robot_frame():
    truth = np.array([2.0, 1.0, math.pi / 2])  # heading along +y
    poses = np.array([[2.0, 3.0, math.pi / 2],        # 2 m ahead
                      [1.0, 1.0, math.pi / 2 + 0.1],  # 1 m to the left (-x), turned left
                      [2.0, 1.0, -3 * math.pi / 2 - 0.2]])  # same place, heading wraps
    e = pose_errors(poses, truth)
    np.testing.assert_allclose(e, [[2.0, 0.0, 0.0], [0.0, 1.0, 0.1], [0.0, 0.0, -0.2]],
                               atol=1e-12)


def test_window_rows_follow_the_increments():
    # a straight path there and back; particle p drifts sideways at rate p, so its revisit
    # error grows with p
    T, J = 201, 5
    x = np.concatenate([np.linspace(0, 20, 101), np.linspace(20, 0, 101)[1:]])
    truth = np.stack([x, np.zeros(T), np.where(np.arange(T) <= 100, 0.0, math.pi)], axis=1)
    drift = np.linspace(0, 1, T)[:, None] * np.arange(J)[None, :] * 0.5
    P = np.repeat(truth[:, None, :], J, axis=1)
    P[:, :, 1] += drift
    revisit = loops.Revisit(i=20, j=180, gap_m=0.0, loop_m=32.0)
    err = [loops.revisit_error(truth, P[:, p], revisit.i, revisit.j) for p in range(J)]
    assert np.all(np.diff(err) > 0)
    # the log weights reward the large-error particles over the first half of the travel and
    # the small-error ones over the second
    arc = arc_length(truth)
    favour_far = np.where(arc < 20, arc, 20.0)[:, None] * np.arange(J)[None, :]
    favour_near = np.where(arc > 20, arc - 20, 0.0)[:, None] * -10.0 * np.arange(J)[None, :]
    rows = window_rows(P, favour_far + favour_near, truth, revisit, window=10.0, from_m=0.0)
    assert [r["from_m"] for r in rows] == [0.0, 10.0, 20.0, 30.0]
    np.testing.assert_allclose([r["rho"] for r in rows], [1.0, 1.0, -1.0, -1.0], atol=1e-12)
    # the second half's weights sit on particle 0, whose pose is the truth
    np.testing.assert_allclose(rows[3]["weighted_error"], [0.0, 0.0, 0.0], atol=1e-9)
    assert rows[3]["ess"] < 1.01
    # unweighted: the particles' mean sideways drift at the window's end; on the way back
    # (heading pi) a drift towards +y is to the robot's right
    np.testing.assert_allclose(rows[3]["mean_error"][1], -drift[-1].mean(), rtol=1e-9)
