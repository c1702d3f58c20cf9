"""Rendered stereo through the real front-end: VO close to ground truth, local maps built."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from gslam_jax.datasets.sim_stereo import load_sim_stereo
from gslam_jax.evaluation import metrics
from gslam_jax.vo.localmap import LocalMapParams


@pytest.fixture(scope="module")
def short_run():
    cv2.setNumThreads(1)
    # The course starts with a 3 s survey stop (15 frames at 5 Hz); 28 frames drive ~1.8 m.
    return load_sim_stereo("mars-yard-a", 0, LocalMapParams(), max_frames=28)


def test_rendered_vo_follows_ground_truth(short_run):
    run, info = short_run
    gt = run.ground_truth
    assert info.summary.vo_failures == 0
    assert np.mean(info.inliers[1:]) > 50
    dist = metrics.path_length(gt)
    assert dist > 1.0
    err = metrics.final_position_error(run.vo_poses(), gt, align="start")
    assert err / dist < 0.03
    steps = np.hypot(*np.diff(gt[:, :2], axis=0).T)
    est = np.hypot(*np.diff(run.vo_poses()[:, :2], axis=0).T)
    assert np.max(np.abs(est - steps)) < 0.03


def test_rendered_run_has_local_maps(short_run):
    run, _ = short_run
    assert run.num_local_maps >= 1
    k = run.local_maps[..., 0]
    assert (k > 0).sum() > 500  # both pairs' dense points landed in cells


def test_bad_pair_index_is_an_error():
    with pytest.raises(ValueError, match="vo_pair"):
        from gslam_jax.datasets.sim_stereo import SimStereoParams
        load_sim_stereo("mars-yard-a", 0, max_frames=2, params=SimStereoParams(vo_pair=2))
