"""The stereo image renderer: determinism, rectified geometry, disparity = f b / z."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from gslam_jax.sim.render import RenderParams, StereoRenderer
from gslam_jax.sim.world import empty_world, smooth_noise
from gslam_jax.vo.geometry import invert
from gslam_jax.vo.stereo import DenseStereoParams, dense_disparity


@pytest.fixture(scope="module")
def flat():
    w = empty_world("mars-yard", 0, (-5.0, 25.0, -15.0, 15.0))
    return StereoRenderer(w, RenderParams(), seed=3)


def test_rendering_is_deterministic(flat):
    a = flat.render_frame(np.array([0.0, 0.0, 0.2]), frame=5)
    b = StereoRenderer(flat.world, RenderParams(), seed=3).render_frame(
        np.array([0.0, 0.0, 0.2]), frame=5)
    for (l1, r1), (l2, r2) in zip(a, b):
        assert l1.dtype == np.uint8 and l1.shape == (384, 512)
        assert np.array_equal(l1, l2) and np.array_equal(r1, r2)
    assert a[0][0].std() > 10  # textured, not blank


def test_rig_is_rectified_with_12cm_baseline(flat):
    rig = flat.rig
    assert rig.size == (512, 384) and rig.baseline == pytest.approx(0.12)
    for left, right in flat.mounts:
        rel = invert(left) @ right
        np.testing.assert_allclose(rel[:3, :3], np.eye(3), atol=1e-12)
        np.testing.assert_allclose(rel[:3, 3], [0.12, 0, 0], atol=1e-12)


def test_sgbm_disparity_on_flat_ground_matches_fb_over_z(flat):
    """On flat ground at z = 0 the depth of pixel (u, v) is known in closed form."""
    cv2.setNumThreads(1)
    pose = np.array([0.0, 0.0, 0.0])
    left, right = flat.render_frame(pose, 0, pairs=(0,))[0]
    disp = dense_disparity(left, right, DenseStereoParams(num_disparities=64, block=5))
    t_wc = flat.camera_poses(pose)[0][0]
    rig = flat.rig
    v, u = np.mgrid[250:370:6, 60:460:6]
    rays = np.stack([(u - rig.cx) / rig.fx, (v - rig.cy) / rig.fy, np.ones(u.shape)], -1)
    d_world = rays @ t_wc[:3, :3].T
    lam = -t_wc[2, 3] / d_world[..., 2]  # ray parameter = camera depth z
    expected = rig.fx * rig.baseline / lam
    got = disp[v, u]
    ok = np.isfinite(got)
    assert ok.mean() > 0.9
    err = got[ok] - expected[ok]
    assert np.median(np.abs(err)) < 0.15 and np.abs(np.median(err)) < 0.1


def test_objects_and_undulating_ground_render(flat):
    w = empty_world("mars-yard", 1, (-5.0, 25.0, -15.0, 15.0))
    w.ground[:] = 0.25 * (smooth_noise(w.shape, 200, np.random.default_rng(0)) - 0.5)
    w.height[:] = w.ground
    from gslam_jax.sim.world import Material, stamp_box
    stamp_box(w, 4.0, 2.5, 1.0, 1.0, 0.3, 1.0, 0.004, Material.BIN)
    r = StereoRenderer(w, seed=0)
    left, _ = r.render_frame(np.array([0.0, 0.0, 0.0]), 0, pairs=(0,))[0]
    assert 20 < left.mean() < 235
