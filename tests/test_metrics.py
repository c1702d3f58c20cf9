"""Rigid fit, error figures and the pose map against independent references (SciPy, brute force)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import minimize
from scipy.special import gammaln

from gslam_jax.evaluation.metrics import (apply_rigid, drift_per_distance, final_position_error,
                                          rigid_fit_2d, rms_after_fit, trajectory_metrics)
from gslam_jax.gridmap.pose_maps import pose_map, vo_only_map
from gslam_jax.rbpf import cells
from gslam_jax.run import Run


def _rms_of(params: np.ndarray, p: np.ndarray, q: np.ndarray) -> float:
    a, tx, ty = params
    c, s = math.cos(a), math.sin(a)
    moved = p @ np.array([[c, -s], [s, c]]).T + np.array([tx, ty])
    return float(np.sqrt(np.mean(np.sum((moved - q) ** 2, axis=1))))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rigid_fit_matches_scipy_optimum(seed: int) -> None:
    rng = np.random.default_rng(seed)
    p = rng.normal(0, 10, (60, 2))
    a = rng.uniform(-np.pi, np.pi)
    c, s = math.cos(a), math.sin(a)
    q = p @ np.array([[c, -s], [s, c]]).T + rng.normal(0, 5, 2) + rng.normal(0, 0.7, p.shape)
    fit = rigid_fit_2d(p, q)
    best = min((minimize(_rms_of, x0=[a0, 0.0, 0.0], args=(p, q), method="Nelder-Mead",
                         options={"xatol": 1e-10, "fatol": 1e-12, "maxiter": 20000})
                for a0 in np.linspace(-3, 3, 7)), key=lambda r: r.fun)
    assert fit.rms == pytest.approx(best.fun, rel=1e-6)
    assert fit.rms <= best.fun + 1e-9


def test_rigid_fit_matches_brute_force_angle_scan() -> None:
    rng = np.random.default_rng(7)
    p = rng.uniform(-20, 20, (40, 2))
    q = rng.uniform(-20, 20, (40, 2))  # unrelated sets: the fit still has one optimum
    fit = rigid_fit_2d(p, q)
    angles = np.linspace(-np.pi, np.pi, 200001)
    c, s = np.cos(angles)[:, None], np.sin(angles)[:, None]
    pc, qc = p - p.mean(0), q - q.mean(0)
    # for a fixed angle the best translation matches the centroids; residual of centred sets
    rx = c * pc[:, 0] - s * pc[:, 1] - qc[:, 0]
    ry = s * pc[:, 0] + c * pc[:, 1] - qc[:, 1]
    brute = np.sqrt(np.mean(rx ** 2 + ry ** 2, axis=1)).min()
    assert fit.rms == pytest.approx(brute, abs=1e-6)


def test_known_rigid_motion_gives_zero_rms() -> None:
    rng = np.random.default_rng(3)
    t = np.linspace(0, 20, 300)
    traj = np.stack([5 * np.cos(t / 3), 3 * np.sin(t / 2), t / 3], axis=1)
    traj += rng.normal(0, 0.01, (300, 3))
    a, shift = 0.7, np.array([12.0, -4.0])
    c, s = math.cos(a), math.sin(a)
    moved = traj.copy()
    moved[:, :2] = traj[:, :2] @ np.array([[c, -s], [s, c]]).T + shift
    moved[:, 2] += a
    fit = rigid_fit_2d(traj, moved)
    assert fit.rms < 1e-10
    assert fit.angle == pytest.approx(a)
    np.testing.assert_allclose(fit.translation, shift, atol=1e-9)
    np.testing.assert_allclose(apply_rigid(traj, fit), moved, atol=1e-9)
    assert rms_after_fit(traj, moved) < 1e-10
    assert final_position_error(traj, moved, align="start") < 1e-9
    assert final_position_error(traj, moved, align="fit") < 1e-9


def test_drift_per_distance_of_a_scale_error() -> None:
    x = np.linspace(0, 100, 501)
    truth = np.stack([x, np.zeros_like(x), np.zeros_like(x)], axis=1)
    est = truth.copy()
    est[:, 0] *= 1.01
    assert drift_per_distance(est, truth) == pytest.approx(0.01)
    m = trajectory_metrics(est, truth, frames=np.array([0, 250, 500]))
    assert m["distance_m"] == pytest.approx(100.0)
    assert m["final_error_m"] == pytest.approx(1.0)
    assert m["drift_pct"] == pytest.approx(1.0)
    assert set(m) >= {"rms_m", "rms_survey_m", "final_error_fit_m"}


def test_bad_inputs_name_the_argument() -> None:
    with pytest.raises(ValueError, match="estimate"):
        rigid_fit_2d(np.zeros(5), np.zeros((5, 2)))
    with pytest.raises(ValueError, match="differ"):
        rigid_fit_2d(np.zeros((5, 2)), np.zeros((4, 2)))
    with pytest.raises(ValueError, match="align"):
        final_position_error(np.zeros((3, 3)), np.zeros((3, 3)), align="end")


def test_expected_std_matches_gamma_formula() -> None:
    k = np.array([0.0, 0.5, 1.0, 2.0, 3.0, 10.0, 57.0])
    S = np.array([0.0, 0.3, 0.2, 0.5, 1.0, 2.0, 4.0])
    got = np.asarray(cells.expected_std(k, S), np.float64)
    assert np.isnan(got[0])
    np.testing.assert_allclose(got[1:3], np.sqrt(S[1:3] / k[1:3]))
    kb, Sb = k[3:], S[3:]
    ref = np.sqrt(Sb / 2) * np.exp(gammaln((kb - 1) / 2) - gammaln(kb / 2))
    np.testing.assert_allclose(got[3:], ref, rtol=1e-5)  # float32
    # and the Monte Carlo mean of h^-1/2 with h ~ Gamma(k/2, rate S/2)
    rng = np.random.default_rng(0)
    h = rng.gamma(10.0 / 2, 2.0 / 2.0, 400000)
    assert np.mean(h ** -0.5) == pytest.approx(got[5], rel=0.01)


def _one_map_run(L: int, res: float, cell: tuple[int, int], pose: np.ndarray) -> Run:
    maps = np.zeros((1, L, L, 3))
    z = np.array([0.1, 0.3, 0.2, 0.6])
    maps[0, cell[0], cell[1]] = [z.size, z.sum(), z @ z]
    return Run(controls=np.zeros((2, 3)), obs_index=np.array([-1, 0], np.int32),
               local_maps=maps, resolution=res, timestamps=np.arange(2.0),
               ground_truth=np.stack([pose, pose]), initial_pose=pose)


def test_pose_map_places_a_cell_where_the_pose_says() -> None:
    L, res = 16, 0.2
    pose = np.array([3.0, -1.0, np.pi / 2])
    # local cell (i, j) centre: x = (i - L/2 + 0.5) res, y likewise
    run = _one_map_run(L, res, (L // 2 + 5, L // 2), pose)
    gm = pose_map(run, np.stack([pose, pose]))
    z = np.array([0.1, 0.3, 0.2, 0.6])
    assert gm.k.sum() == pytest.approx(3.0)
    assert gm.S.sum() == pytest.approx(np.sum((z - z.mean()) ** 2))
    i, j = np.unravel_index(np.argmax(gm.k), gm.k.shape)
    centre = np.array(gm.origin) + (np.array([i, j]) + 0.5) * res
    # local x = 1.1 m forward; heading +90 deg -> world +y; local y = 0.1 m -> world -x
    np.testing.assert_allclose(centre, [3.0 - 0.1, -1.0 + 1.1], atol=res / 2 + 1e-9)
    assert np.isnan(gm.expected_std()).sum() == gm.k.size - 1


def test_vo_only_map_uses_the_integrated_controls() -> None:
    run = _one_map_run(16, 0.2, (8, 8), np.array([1.0, 2.0, 0.0]))
    run = run._replace(controls=np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]]))
    a = vo_only_map(run)
    b = pose_map(run, run.vo_poses())
    np.testing.assert_array_equal(a.k, b.k)
    assert a.origin == b.origin


def test_drift_over_known_frames_by_hand():
    from gslam_jax.evaluation.metrics import drift_over_known_frames

    # Truth: 10 m east then 10 m north (20 m); the estimate ends 0.5 m off (3-4-5 x 0.1).
    gt = np.array([[0, 0, 0], [10, 0, np.pi / 2], [10, 10, np.pi / 2]], float)
    est = gt.copy()
    est[-1, :2] += [0.3, 0.4]
    out = drift_over_known_frames({"vo": est, "same": gt}, gt)
    assert out["gt_distance_m"] == pytest.approx(20.0)
    assert out["vo_drift_pct"] == pytest.approx(2.5)  # 0.5 m / 20 m
    assert out["same_drift_pct"] == pytest.approx(0.0, abs=1e-12)
    # Anchored at the first pose: an estimate in another frame (rotated 90 deg, shifted)
    # with the same shape has no drift.
    c, s = 0.0, 1.0
    moved = np.c_[gt[:, 0] * c - gt[:, 1] * s + 5, gt[:, 0] * s + gt[:, 1] * c - 2,
                  gt[:, 2] + np.pi / 2]
    assert drift_over_known_frames({"m": moved}, gt)["m_drift_pct"] == pytest.approx(0, abs=1e-9)
    # NaN rows are skipped: the distance is bridged over the gap (0,0) -> (10,10).
    gap = gt.copy()
    gap[1] = np.nan
    out = drift_over_known_frames({"vo": est}, gap)
    assert out["gt_distance_m"] == pytest.approx(np.hypot(10, 10))
    assert out["vo_drift_pct"] == pytest.approx(100 * 0.5 / np.hypot(10, 10))
    assert drift_over_known_frames({"vo": est}, np.full((3, 3), np.nan)) == {}


def test_ground_truth_in_map_frame_starts_on_the_path():
    from gslam_jax.evaluation.metrics import ground_truth_in_map_frame

    gt = np.array([[np.nan] * 3, [1, 1, 0], [2, 1, 0]], float)
    path = np.array([[0, 0, 0], [5, 5, np.pi / 2], [5, 6, np.pi / 2]], float)
    moved = ground_truth_in_map_frame(gt, path)
    assert np.all(np.isnan(moved[0]))
    np.testing.assert_allclose(moved[1:], path[1:], atol=1e-12)  # same shape: on the path
