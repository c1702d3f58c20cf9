"""VO failure handling: fallback increments, slip ratio, gravity tilt correction (paper sec. 4)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from gslam_jax.vo.fallback import GRAVITY, correct_tilt, fallback_increment, level_rotation, slip_ratio


def test_slip_ratio_definition():
    s = slip_ratio(np.array([1.0, 1.0, -1.0, 0.0]), np.array([1.0, 0.0, -0.5, 0.3]))
    np.testing.assert_allclose(s[:3], [0.0, 1.0, -0.5])  # bogged wheels spinning -> 1
    assert np.isnan(s[3])


def test_fallback_sources():
    prev = np.array([0.5, 0.0, 0.01])
    u, src = fallback_increment(prev, np.array([0.4, 0.01, 0.05]), 0.02)
    assert src == "wheel+imu" and np.allclose(u, [0.4, 0.01, 0.02])
    u, src = fallback_increment(prev, np.array([0.4, 0.01, 0.05]), None)
    assert src == "wheel" and np.allclose(u, [0.4, 0.01, 0.05])
    u, src = fallback_increment(prev, None, 0.03)
    assert src == "imu" and np.allclose(u, [0.5, 0.0, 0.03])
    u, src = fallback_increment(prev, None, None)
    assert src == "hold" and np.allclose(u, prev)


def test_tilt_correction_levels_attitude_and_keeps_heading():
    true = Rotation.from_euler("ZYX", [40.0, 0.0, 0.0], degrees=True).as_matrix()  # level, yaw 40
    est = Rotation.from_euler("ZYX", [40.0, 4.0, -3.0], degrees=True).as_matrix()  # drifted tilt
    accel = true.T @ np.array([0.0, 0.0, GRAVITY])  # at rest the IMU reads +g along world up
    for _ in range(200):
        est, applied = correct_tilt(est, accel, gain=0.05)
        assert applied
    tilt = np.degrees(Rotation.from_matrix(level_rotation(est)).magnitude())
    assert tilt < 0.01
    yaw = np.degrees(np.arctan2(est[1, 0], est[0, 0]))
    assert abs(yaw - 40.0) < 0.2  # the horizontal-axis correction moves heading to 2nd order only


def test_tilt_correction_gated_during_acceleration():
    est = Rotation.from_euler("ZYX", [0.0, 4.0, 0.0], degrees=True).as_matrix()
    out, applied = correct_tilt(est, np.array([3.0, 0.0, GRAVITY]), gate=0.3)
    assert not applied and np.array_equal(out, est)
