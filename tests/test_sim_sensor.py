"""The point sensor against closed-form geometry: flat-plane height spread, occlusion, gates."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gslam_jax.sim.sensor import PointSensor, SensorParams, depth_noise_std
from gslam_jax.sim.world import Material, empty_world, stamp_box


def _flat_world(size: float = 30.0):
    w = empty_world("test", 0, (-size, size, -size, size), 0.05, base_rough=0.0)
    return w


def _collect(sensor: PointSensor, pose: np.ndarray, frames: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.concatenate([sensor.observe(pose, rng) for _ in range(frames)])


def test_noise_free_flat_plane_is_exactly_flat() -> None:
    p = SensorParams(disparity_std=0.0, dropout=0.0)
    pts = _collect(PointSensor(_flat_world(), p), np.array([0.0, 0.0, 0.3]), 3)
    assert len(pts) > 1000
    np.testing.assert_allclose(pts[:, 2], 0.0, atol=1e-5)
    horiz = np.hypot(pts[:, 0], pts[:, 1])
    assert horiz.max() <= p.max_range + 1e-9 and horiz.min() >= p.min_range - 1e-9
    assert np.abs(np.arctan2(pts[:, 1], pts[:, 0])).max() <= p.half_fov + 1e-3


def test_flat_plane_cell_variance_is_the_stereo_range_noise() -> None:
    """On a flat plane without surface roughness the per-cell height variance must be the stereo
    noise alone: a ground point seen from height h at depth z (optical axis) has height std
    h * sigma_z / z = h z sigma_d / (f b)."""
    p = SensorParams(dropout=0.0, disparity_std=0.3)
    sensor = PointSensor(_flat_world(), p)
    pts = _collect(sensor, np.array([0.0, 0.0, 0.0]), 60, seed=1)
    res = 0.16
    i = np.floor(pts[:, 0] / res).astype(int)
    j = np.floor(pts[:, 1] / res).astype(int)
    key = i * 10000 + j
    uniq, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    mean = np.bincount(inv, pts[:, 2]) / cnt
    var = np.bincount(inv, pts[:, 2] ** 2) / cnt - mean ** 2
    ci, cj = uniq // 10000, uniq % 10000
    ci = np.where(cj > 5000, ci + 1, ci)  # undo floor-division of negative keys
    cj = np.where(cj > 5000, cj - 10000, cj)
    cx, cy = (ci + 0.5) * res, (cj + 0.5) * res
    # independent prediction from the cell centre and the camera geometry
    yaw = np.where(np.arctan2(cy, cx) >= 0, p.camera_yaw, -p.camera_yaw)
    cp, sp = math.cos(p.camera_pitch), math.sin(p.camera_pitch)
    depth = cx * np.cos(yaw) * cp + cy * np.sin(yaw) * cp + p.camera_height * sp
    pred_std = p.camera_height * depth_noise_std(depth, p.focal_px, p.baseline,
                                                 p.disparity_std) / depth
    rho = np.hypot(cx, cy)
    for lo, hi in ((1.5, 3.0), (3.0, 5.0), (5.0, 7.0)):
        sel = (cnt >= 15) & (rho >= lo) & (rho < hi)
        assert sel.sum() > 30, (lo, hi, sel.sum())
        ratio = var[sel].mean() / (pred_std[sel] ** 2).mean()
        assert ratio == pytest.approx(1.0, abs=0.15), (lo, hi, ratio)


def test_depth_noise_grows_with_range_squared() -> None:
    s = depth_noise_std(np.array([1.0, 2.0, 4.0]), 400.0, 0.12, 0.2)
    np.testing.assert_allclose(s[1:] / s[:-1], 4.0)
    assert s[0] == pytest.approx(0.2 / (400 * 0.12))


def test_wall_occludes_what_is_behind_it() -> None:
    w = _flat_world()
    stamp_box(w, 4.0, 0.0, 0.4, 6.0, 0.0, 3.0, 0.0, Material.BUILDING)  # wall x in [3.8, 4.2]
    p = SensorParams(dropout=0.0, disparity_std=0.0)
    pts = _collect(PointSensor(w, p), np.array([0.0, 0.0, 0.0]), 5)
    behind = pts[(np.abs(pts[:, 1]) < 1.5) & (pts[:, 0] > 4.3)]
    assert len(behind) == 0
    on_wall = pts[(np.abs(pts[:, 1]) < 2.5) & (np.abs(pts[:, 0] - 3.8) < 0.06)]
    assert len(on_wall) > 50
    assert on_wall[:, 2].max() > 1.5  # the face spans a tall range of heights
    assert np.var(on_wall[:, 2]) > 0.1


def test_dropouts_thin_the_points() -> None:
    w = _flat_world()
    full = _collect(PointSensor(w, SensorParams(dropout=0.0)), np.zeros(3), 5)
    thin = _collect(PointSensor(w, SensorParams(dropout=0.5)), np.zeros(3), 5)
    assert 0.4 < len(thin) / len(full) < 0.6


def test_bad_sensor_params_are_named() -> None:
    with pytest.raises(ValueError, match="baseline"):
        SensorParams(baseline=0.0)
    with pytest.raises(ValueError, match="dropout"):
        SensorParams(dropout=1.0)
