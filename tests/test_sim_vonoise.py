"""VO noise: eqs. 1-3 statistics with known alphas, failures, and VO-only error in range."""

from __future__ import annotations

import numpy as np
import pytest

from gslam_jax.datasets.sim import simulate_odometry, simulate_run
from gslam_jax.evaluation.metrics import rms_after_fit
from gslam_jax.run import integrate_controls
from gslam_jax.sim import (VONoiseParams, apply_vo_noise, course_names, drive, make_course,
                           true_increments)
from gslam_jax.vo.localmap import LocalMapParams

QUIET = dict(scale_bias_std=0.0, heading_bias_std=0.0, failure_rate=0.0)


def _increments(n: int, rng: np.random.Generator) -> np.ndarray:
    d = rng.uniform(0.05, 0.2, n)
    a = rng.uniform(-0.3, 0.3, n)
    return np.stack([d * np.cos(a), d * np.sin(a), rng.uniform(-0.1, 0.1, n)], axis=1)


def test_true_increments_integrate_back_to_the_poses() -> None:
    traj = drive(make_course("mars-yard-b", 0))
    u = true_increments(traj.poses)
    np.testing.assert_allclose(u[0], 0.0)
    np.testing.assert_allclose(integrate_controls(u, traj.poses[0]), traj.poses, atol=1e-9)


def test_zero_noise_is_the_truth() -> None:
    zero = VONoiseParams(alpha_d=0.0, alpha_theta_d=0.0, alpha_theta=0.0, **QUIET)
    u = _increments(500, np.random.default_rng(0))
    out, draw = apply_vo_noise(u, zero, np.random.default_rng(1))
    np.testing.assert_allclose(out, u)
    assert not draw.vo_failed.any()


def test_white_noise_follows_eqs_2_and_3() -> None:
    p = VONoiseParams(alpha_d=0.05, alpha_theta_d=0.02, alpha_theta=0.1, **QUIET)
    u = _increments(40000, np.random.default_rng(2))
    out, _ = apply_vo_noise(u, p, np.random.default_rng(3))
    d = np.hypot(u[:, 0], u[:, 1])
    along = np.hypot(out[:, 0], out[:, 1]) - d
    across = np.arctan2(out[:, 1], out[:, 0]) - np.arctan2(u[:, 1], u[:, 0])
    assert np.std(along / (p.alpha_d * d)) == pytest.approx(1.0, abs=0.03)
    np.testing.assert_allclose(across, 0.0, atol=1e-12)  # no noise across the direction of travel
    sigma_th = p.alpha_theta_d * d + p.alpha_theta * np.abs(u[:, 2])
    assert np.std((out[:, 2] - u[:, 2]) / sigma_th) == pytest.approx(1.0, abs=0.03)


def test_failures_are_flagged_and_use_wheel_odometry() -> None:
    p = VONoiseParams(alpha_d=0.0, alpha_theta_d=0.0, alpha_theta=0.0, scale_bias_std=0.0,
                      heading_bias_std=0.0, failure_rate=0.02, wheel_slip_std=0.0)
    u = _increments(5000, np.random.default_rng(4))
    out, draw = apply_vo_noise(u, p, np.random.default_rng(5))
    f = draw.vo_failed
    assert 0.02 < f.mean() < 0.2
    ratio = np.hypot(out[:, 0], out[:, 1]) / np.hypot(u[:, 0], u[:, 1])
    np.testing.assert_allclose(ratio[f], 1.0 + p.wheel_slip_mean)
    np.testing.assert_allclose(ratio[~f], 1.0)


def test_bad_params_are_named() -> None:
    with pytest.raises(ValueError, match="alpha_d"):
        VONoiseParams(alpha_d=-0.1)
    with pytest.raises(ValueError, match="increments"):
        apply_vo_noise(np.zeros((4, 2)), VONoiseParams(), np.random.default_rng(0))


@pytest.mark.parametrize("name", course_names())
def test_vo_only_error_is_in_the_papers_range(name: str) -> None:
    """Mean VO-only RMS over seeds within the span of Table I's VO column (0.42-1.98 m), with
    slack for the spread between seeds; drawn exactly as simulate_run draws it."""
    rms = []
    for seed in range(4):
        odo = simulate_odometry(name, seed)
        rms.append(rms_after_fit(odo.vo_poses(), odo.trajectory.poses))
    assert 0.25 <= np.mean(rms) <= 2.5, rms


def test_odometry_matches_the_full_simulation() -> None:
    odo = simulate_odometry("maze", 4, max_frames=60)
    run, _ = simulate_run("maze", 4, LocalMapParams(max_range=4.0), max_frames=60)
    np.testing.assert_array_equal(odo.controls, run.controls)
    np.testing.assert_array_equal(odo.vo_draw.vo_failed, run.vo_failed)


def test_a_truncated_course_is_a_prefix_of_the_full_one() -> None:
    """max_frames cuts the drawn noise, it does not redraw it: a quick run of N frames sees the
    same VO as the first N frames of the full run with the same seed."""
    short, full = simulate_odometry("maze", 3, max_frames=200), simulate_odometry("maze", 3)
    np.testing.assert_array_equal(short.controls, full.controls[:200])
    np.testing.assert_array_equal(short.vo_draw.vo_failed, full.vo_draw.vo_failed[:200])
    np.testing.assert_array_equal(short.vo_draw.scale_bias, full.vo_draw.scale_bias[:200])
    np.testing.assert_array_equal(short.trajectory.poses, full.trajectory.poses[:200])
