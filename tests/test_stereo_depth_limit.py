"""The front-end's depth limit: points whose depth error would exceed ``max_depth_error``."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from gslam_jax.datasets.sim_stereo import SimStereoParams, load_sim_stereo
from gslam_jax.vo.calib import RectifiedRig
from gslam_jax.vo.frontend import FrontEndParams
from gslam_jax.vo.localmap import LocalMapParams
from gslam_jax.vo.stereo import DenseStereoParams, depth_limit


def _rig(fx: float, baseline: float) -> RectifiedRig:
    k = np.array([[fx, 0.0, 320.0], [0.0, fx, 240.0], [0.0, 0.0, 1.0]])
    p1 = np.hstack([k, np.array([[-fx * baseline], [0.0], [0.0]])])
    return RectifiedRig.from_projections(np.hstack([k, np.zeros((3, 1))]), p1, (640, 480), "t")


@pytest.mark.parametrize("fx, baseline, error, sigma", [(370.0, 0.12, 0.2, 0.25),
                                                         (718.9, 0.54, 0.2, 0.25),
                                                         (458.0, 0.11, 0.1, 0.5)])
def test_depth_error_at_the_limit_is_the_one_asked_for(fx, baseline, error, sigma):
    """Monte Carlo: disparities drawn with the assumed noise at the limit's depth, triangulated
    as the front-end does (z = f b / d), spread by the asked-for error (first order)."""
    rig = _rig(fx, baseline)
    z = depth_limit(rig, DenseStereoParams(max_depth_error=error, disparity_std=sigma))
    fb = fx * baseline
    d = fb / z + sigma * np.random.default_rng(0).standard_normal(400_000)
    assert np.std(fb / d) == pytest.approx(error, rel=0.03)


def test_depth_limit_needs_positive_settings():
    with pytest.raises(ValueError, match="max_depth_error and disparity_std must be positive"):
        depth_limit(_rig(370.0, 0.12), DenseStereoParams(max_depth_error=0.0))
    assert depth_limit(_rig(370.0, 0.12), DenseStereoParams(max_depth_error=np.inf)) == np.inf


def _farthest_cell(max_depth_error: float | None) -> float:
    """Horizontal distance (m) from the robot of the farthest observed cell centre of frame 0's
    local map, rendered on Mars Yard A."""
    cv2.setNumThreads(1)
    stereo = (DenseStereoParams() if max_depth_error is None
              else DenseStereoParams(max_depth_error=max_depth_error))
    params = SimStereoParams(frontend=FrontEndParams(stereo=stereo))
    lm = LocalMapParams(lattice="map")
    run, _ = load_sim_stereo("mars-yard-a", 0, lm, max_frames=1, params=params)
    i, j = np.nonzero(run.local_maps[0, ..., 0] > 0)
    centre = (np.stack([i, j], 1) - lm.size // 2 + 0.5) * lm.resolution
    return float(np.hypot(*centre.T).max())


def test_front_end_makes_no_point_beyond_the_depth_limit():
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
