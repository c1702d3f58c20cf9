"""The disparity noise measured from consecutive frames, and the front-end's depth-error limit."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from gslam_jax.datasets.sim_stereo import SimStereoParams, load_sim_stereo
from gslam_jax.vo.calib import RectifiedRig
from gslam_jax.vo.disparity_noise import (DISPARITY_EDGES, DisparityNoise, depth_errors,
                                          temporal_residuals)
from gslam_jax.vo.frontend import FrontEndParams
from gslam_jax.vo.geometry import make_transform
from gslam_jax.vo.localmap import LocalMapParams
from gslam_jax.vo.stereo import DenseStereoParams

W, H = 320, 240


def _rig(fx: float = 370.0, baseline: float = 0.12) -> RectifiedRig:
    k = np.array([[fx, 0.0, (W - 1) / 2], [0.0, fx, (H - 1) / 2], [0.0, 0.0, 1.0]])
    p1 = np.hstack([k, np.array([[-fx * baseline], [0.0], [0.0]])])
    return RectifiedRig.from_projections(np.hstack([k, np.zeros((3, 1))]), p1, (W, H), "t")


def _ground_disparity(rig: RectifiedRig, t_world_cam: np.ndarray) -> np.ndarray:
    """Exact disparity of the plane y_world = 1 (the ground 1 m under a level camera whose
    y axis points down), NaN where a ray misses it."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    rays = np.stack([(u - rig.cx) / rig.fx, (v - rig.cy) / rig.fy, np.ones_like(u)], -1)
    r, c = t_world_cam[:3, :3], t_world_cam[:3, 3]
    dy = rays @ r[1]  # world y of each ray per unit camera depth
    z = (1.0 - c[1]) / dy  # camera depth where the ray meets the plane
    return np.where((dy > 1e-6) & (z > 0), rig.fx * rig.baseline / z, np.nan)


def _pose(yaw: float, forward: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return make_transform(np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]),
                          [0.05 * forward, 0.0, forward])


def test_residuals_vanish_for_exact_disparities_of_a_plane():
    """A plane's disparity is affine in the pixel, so the bilinear read is exact."""
    rig = _rig()
    prev, cur = _pose(0.0, 0.0), _pose(0.03, 0.4)
    t_prev_cur = np.linalg.inv(prev) @ cur
    pred, res = temporal_residuals(_ground_disparity(rig, prev), _ground_disparity(rig, cur),
                                   t_prev_cur, rig, stride=2)
    assert len(pred) > 5000
    np.testing.assert_allclose(res, 0.0, atol=1e-6)
    assert pred.max() > 10.0
    capped, _ = temporal_residuals(_ground_disparity(rig, prev), _ground_disparity(rig, cur),
                                   t_prev_cur, rig, stride=2, max_disparity=10.0)
    assert capped.max() < 10.0 and len(capped) == np.sum(pred < 10.0)
    # a wrong motion (the camera 5 cm lower than it was) leaves residuals: the check can fail
    lower = cur.copy()
    lower[1, 3] += 0.05
    _, off = temporal_residuals(_ground_disparity(rig, prev), _ground_disparity(rig, cur),
                                np.linalg.inv(prev) @ lower, rig, stride=2)
    assert np.median(np.abs(off)) > 0.05


def _smooth_noise(rng: np.random.Generator) -> np.ndarray:
    """Unit-variance Gaussian noise correlated over a few pixels, as a block matcher's errors
    are (a 5 x 5 window)."""
    white = rng.standard_normal((H, W)).astype(np.float32)
    smooth = cv2.GaussianBlur(white, (0, 0), 2.0).astype(np.float64)
    return smooth / smooth.std()


def test_noise_is_recovered_per_disparity_band():
    """Gaussian noise of a known sigma per band (0.6 px under 8 px, 0.2 px over), drawn
    independently in each frame, comes back within 6 % once enough frames are in."""
    rig = _rig()
    rng = np.random.default_rng(0)
    noise = DisparityNoise(forget=0.95)
    truth = lambda d: np.where(d < 8.0, 0.6, 0.2)  # noqa: E731
    prev = None
    for t in range(12):
        pose = _pose(0.01 * t, 0.3 * t)
        d = _ground_disparity(rig, pose)
        d = d + truth(np.nan_to_num(d)) * _smooth_noise(rng)
        if prev is not None:
            noise.update(*temporal_residuals(prev[0], d, np.linalg.inv(prev[1]) @ pose, rig))
        prev = (d, pose)
    sig = noise.band_sigmas()
    full = noise.counts.sum(1) >= noise.min_samples
    centres = np.sqrt(DISPARITY_EDGES[:-1] * DISPARITY_EDGES[1:])
    inner = full[1:-1] & (np.abs(np.log2(centres / 8.0)) > 0.5)  # bands clear of the 8 px step
    assert inner.sum() >= 4
    np.testing.assert_allclose(sig[1:-1][inner], truth(centres[inner]), rtol=0.06)
    assert np.all(sig[~full] == noise.prior_std)


def test_band_sigma_is_the_median_absolute_residual():
    """Against numpy's median on the same residuals (no forgetting), to the histogram step."""
    rng = np.random.default_rng(1)
    pred = rng.uniform(3.0, 60.0, 20000)
    res = rng.laplace(0.0, 0.3, pred.size) * (1 + 20 / pred)
    noise = DisparityNoise(forget=1.0)
    noise.update(pred, res)
    band = np.searchsorted(DISPARITY_EDGES, pred)
    for b in np.unique(band):
        m = band == b
        if m.sum() < noise.min_samples:
            continue
        expected = 1.4826 * np.median(np.abs(res[m])) / np.sqrt(2)
        assert noise.band_sigmas()[b] == pytest.approx(expected, abs=0.02)


@pytest.mark.parametrize("fx, baseline, error, sigma", [(370.0, 0.12, 0.2, 0.25),
                                                         (718.9, 0.54, 0.2, 0.25),
                                                         (458.0, 0.11, 0.1, 0.5)])
def test_depth_error_is_the_spread_of_triangulated_depth(fx, baseline, error, sigma):
    """Monte Carlo: disparities drawn with the noise at the depth where ``depth_errors`` says
    ``error``, triangulated as the front-end does (z = f b / d), spread by ``error``."""
    rig = _rig(fx, baseline)
    fb = fx * baseline
    z = np.sqrt(error * fb / sigma)
    noise = DisparityNoise(prior_std=sigma)  # nothing measured: the prior in every band
    assert depth_errors(np.array([[0.3, -0.2, z]]), rig, noise)[0] == pytest.approx(error)
    d = fb / z + sigma * np.random.default_rng(0).standard_normal(400_000)
    assert np.std(fb / d) == pytest.approx(error, rel=0.03)


def _farthest_cell(max_depth_error: float | None) -> float:
    """Horizontal distance (m) from the robot of the farthest observed cell centre of frame 0's
    local map, rendered on Mars Yard A. At frame 0 nothing is measured yet: the prior holds."""
    cv2.setNumThreads(1)
    stereo = (DenseStereoParams() if max_depth_error is None
              else DenseStereoParams(max_depth_error=max_depth_error))
    params = SimStereoParams(frontend=FrontEndParams(stereo=stereo))
    lm = LocalMapParams(lattice="map")
    run, _ = load_sim_stereo("mars-yard-a", 0, lm, max_frames=1, params=params)
    i, j = np.nonzero(run.local_maps[0, ..., 0] > 0)
    centre = (np.stack([i, j], 1) - lm.size // 2 + 0.5) * lm.resolution
    return float(np.hypot(*centre.T).max())


def test_front_end_makes_no_point_beyond_the_depth_error():
    """The limit is on the optical depth; an image corner's ray reaches 1.32 times as far."""
    rig_fb = 370.0 * 0.12  # the rendered rig (RenderParams: 512 x 384, f 370 px)
    corner = np.hypot(np.hypot(255.5 / 370.0, 191.5 / 370.0), 1.0)
    margin = 0.16 * np.sqrt(0.5) + 0.12  # half a cell's diagonal and a baseline
    for error in (0.05, 0.2):
        limit = np.sqrt(error * rig_fb / 0.25)  # 3.0 m, 6.0 m
        far = _farthest_cell(error)
        assert limit - 1.0 < far <= limit * corner + margin, (error, far, limit)
    # the default, no limit: out to the local map's range
    assert _farthest_cell(None) > 6.0 * corner + margin


def test_measured_noise_against_the_closed_form_truth_on_rendered_ground():
    """Rendered flat ground, where every pixel's true disparity is known in closed form: the
    frame-to-frame estimate sees the part of SGBM's error that changes between frames, and
    misses what stays with the texture. Measured 0.34-1.28x the true sigma per band; a lost
    sqrt(2) or 1.4826 would leave this range."""
    from gslam_jax.sim.render import RenderParams, StereoRenderer
    from gslam_jax.sim.world import empty_world
    from gslam_jax.vo.geometry import invert
    from gslam_jax.vo.stereo import dense_disparity

    cv2.setNumThreads(1)
    ren = StereoRenderer(empty_world("mars-yard", 0, (-5.0, 25.0, -15.0, 15.0)),
                         RenderParams(), seed=3)
    rig = ren.rig
    fb = rig.fx * rig.baseline
    noise = DisparityNoise(forget=1.0)
    errors, truths, prev = [], [], None
    for t in range(6):
        pose = np.array([0.15 * t, 0.0, 0.0])
        disp = dense_disparity(*ren.render_frame(pose, t, pairs=(0,))[0], DenseStereoParams())
        t_wc = ren.camera_poses(pose)[0][0]
        v, u = np.mgrid[0:disp.shape[0]:2, 0:disp.shape[1]:2]
        rays = np.stack([(u - rig.cx) / rig.fx, (v - rig.cy) / rig.fy, np.ones(u.shape)], -1)
        depth = -t_wc[2, 3] / (rays @ t_wc[2, :3])  # camera depth where the ray meets z = 0
        truth = np.where(depth > 0, fb / depth, np.nan)
        got = disp[::2, ::2]
        ok = np.isfinite(got) & np.isfinite(truth)
        errors.append(got[ok] - truth[ok])
        truths.append(truth[ok])
        if prev is not None:
            noise.update(*temporal_residuals(prev[0], disp, invert(prev[1]) @ t_wc, rig))
        prev = (disp, t_wc)
    err, truth = np.concatenate(errors), np.concatenate(truths)
    band = np.searchsorted(DISPARITY_EDGES, truth)
    measured = noise.band_sigmas()
    ratios = []
    for b in np.unique(band):
        m = band == b
        if m.sum() < 2000 or noise.counts[b].sum() < noise.min_samples:
            continue
        e = err[m]
        true_sigma = 1.4826 * np.median(np.abs(e - np.median(e)))
        ratios.append(measured[b] / true_sigma)
    assert len(ratios) >= 6
    assert 0.25 < min(ratios) and max(ratios) < 1.5, np.round(ratios, 2)


def test_disparity_truth_marches_rays_to_the_ground_and_a_wall():
    """``experiments.disparity_truth``'s truth against the closed form: from 1 m over flat
    ground (z = 0) a ray with downward component dz meets it at range 1 / dz, unless a 2 m wall
    across x = 5 m stops it first, at range 5 / (its x component)."""
    from experiments.disparity_truth import MARCH_STEP, true_ranges
    from gslam_jax.sim.world import empty_world

    world = empty_world("mars-yard", 0, (-5.0, 25.0, -15.0, 15.0))
    wall_x = 5.0
    ix = int(round((wall_x - world.origin[0]) / world.resolution))
    world.height[ix:] = 2.0  # every cell whose centre lies beyond x = 5 m
    rng = np.random.default_rng(2)
    yaw = rng.uniform(-0.6, 0.6, 300)
    down = rng.uniform(0.05, 0.8, 300)  # ground 1.25-20 m away
    dirs = np.stack([np.cos(down) * np.cos(yaw), np.cos(down) * np.sin(yaw), -np.sin(down)], 1)
    got = true_ranges(world, np.array([0.0, 0.0, 1.0]), dirs)
    expected = np.minimum(1.0 / np.sin(down), wall_x / dirs[:, 0])
    assert 30 < np.sum(wall_x / dirs[:, 0] < 1.0 / np.sin(down)) < 270  # both kinds of hit
    # within a march step, and the bilinear ramp of the wall's edge (one raster cell)
    slack = MARCH_STEP + world.resolution / dirs[:, 0]
    assert np.all(got >= expected - slack) and np.all(got <= expected + slack)
    assert np.isnan(true_ranges(world, np.array([0.0, 0.0, 3.0]), np.array([[0.0, 1.0, 0.0]])))[0]


def test_depth_edges_against_a_loop_over_windows():
    """``drop_depth_edges`` against the definition, pixel by pixel: the 5 x 5 window (clipped
    at the image's border) spans at most ``ratio`` times the pixel's disparity and holds no
    unmatched pixel."""
    from gslam_jax.vo.stereo import drop_depth_edges

    rng = np.random.default_rng(3)
    disp = rng.uniform(4.0, 6.0, (30, 40)).astype(np.float32)
    disp[:, 25:] *= 2.0  # a depth edge
    disp[rng.random(disp.shape) < 0.02] = np.nan
    out = drop_depth_edges(disp, 0.3)
    zeroed = np.nan_to_num(disp, nan=0.0)
    for i in range(disp.shape[0]):
        for j in range(disp.shape[1]):
            w = zeroed[max(0, i - 2):i + 3, max(0, j - 2):j + 3]
            keep = zeroed[i, j] > 0 and w.max() - w.min() <= 0.3 * zeroed[i, j]
            assert np.isfinite(out[i, j]) == keep, (i, j)
            if keep:
                assert out[i, j] == disp[i, j]
    assert np.isnan(out[:, 23:27]).all()  # the edge's flying pixels
    assert drop_depth_edges(disp, np.inf) is disp
