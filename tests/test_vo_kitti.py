"""Stereo VO on 51 real KITTI frames (issue 4 acceptance: final position error <= 1% of distance)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from gslam_jax.datasets.kitti import read_kitti_calib, read_kitti_poses
from gslam_jax.datasets.reading import read_image
from gslam_jax.vo.estimate import Camera
from gslam_jax.vo.geometry import invert, rotation_angle
from gslam_jax.vo.odometry import StereoVO

SEQ = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti-stereo-51"


@pytest.fixture(scope="module")
def kitti():
    if not (SEQ / "sequences" / "seq1").is_dir():
        pytest.skip(f"real KITTI frames not found at {SEQ} (see shared/data/README.md)")
    cv2.setNumThreads(1)
    seq = SEQ / "sequences" / "seq1"
    lefts = sorted((seq / "image_0").glob("*.png"))
    pairs = [(read_image(p), read_image(seq / "image_1" / p.name)) for p in lefts]
    h, w = pairs[0][0].shape
    rig = read_kitti_calib(seq / "calib.txt", (w, h))
    return pairs, Camera(rig.fx, rig.fy, rig.cx, rig.cy, rig.baseline), read_kitti_poses(
        SEQ / "poses" / "seq1.txt")


def _run(pairs, cam):
    vo = StereoVO(cam)
    results = [vo.step(l, r) for l, r in pairs]
    pose, poses = np.eye(4), [np.eye(4)]
    for res in results[1:]:
        assert res.ok, res.reason
        pose = pose @ res.transform
        poses.append(pose)
    return np.stack(poses), results


def _errors(poses, gt):
    dist = np.sum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1))
    final = np.linalg.norm(poses[-1, :3, 3] - gt[-1, :3, 3]) / dist
    rot = [np.degrees(rotation_angle(invert(invert(gt[t - 1]) @ gt[t])
                                     @ (invert(poses[t - 1]) @ poses[t])))
           for t in range(1, len(gt))]
    return final, float(np.mean(rot)), dist


def test_kitti_vo_drift_within_one_percent(kitti):
    pairs, cam, gt = kitti
    poses, results = _run(pairs, cam)
    final, rot, dist = _errors(poses, gt)
    inliers = np.mean([r.n_inliers for r in results[1:]])
    print(f"\nKITTI 51 frames, {dist:.1f} m: final position error {100 * final:.2f}% of distance, "
          f"mean per-frame rotation error {rot:.4f} deg, mean inliers {inliers:.0f}")
    assert final <= 0.01
    assert rot < 0.1
    assert inliers >= 50


def test_kitti_bound_rejects_a_miscalibrated_tracker(kitti):
    """The 1% bound has teeth: the same tracker with a 3% baseline error fails it."""
    pairs, cam, gt = kitti
    poses, _ = _run(pairs[:21], cam._replace(baseline=cam.baseline * 1.03))
    final, _, _ = _errors(poses, gt[:21])
    assert final > 0.01
