"""Degenerate inputs that used to print raw NumPy RuntimeWarnings ("Mean of empty slice",
"overflow encountered"): each is now a guarded computation (run with warnings as errors)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from gslam_jax.vo.estimate import Camera, estimate_motion


@pytest.mark.parametrize("baseline", [1e12, 1e15])
def test_motion_from_a_kilometre_scale_baseline_warns_nothing(baseline):
    """A calibration with an absurd baseline (a typo in T_BS) put depths near 1e14 m and
    overflowed the conditioning ratio; it is now infinite (degenerate: VO falls back)."""
    cam = Camera(457.6, 456.1, 380.0, 255.2, baseline)
    rng = np.random.default_rng(0)
    n = 2000  # enough matches that the largest eigenvalue of J^T J exceeds 1.8e8
    ja = np.column_stack([rng.uniform(50, 700, n), rng.uniform(50, 430, n),
                          rng.uniform(2, 60, n)])
    jb = ja + rng.normal(0, 0.3, ja.shape)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        est = estimate_motion(cam, ja, jb, gate_px=2.0)
    assert est.condition == np.inf  # degenerate geometry, refused by the VO's gate


def test_one_frame_simulation_summary_has_no_rate():
    """``gslam run --max-frames 1`` took the median of no frame intervals for rate_hz."""
    from gslam_jax.datasets.sim import simulate_run

    run, info = simulate_run("mars-yard-a", 0, max_frames=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        summary = info.summary()
    assert run.num_frames == 1 and summary["rate_hz"] is None
    _, two = simulate_run("mars-yard-a", 0, max_frames=2)
    assert two.summary()["rate_hz"] == pytest.approx(
        1.0 / float(np.diff(two.trajectory.timestamps)[0]))
