"""EuRoC adapter on 20 real frames of a standing MAV: rectification, static VO, gravity, bad calib."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from gslam_jax.datasets.euroc import EurocParams, euroc_frontend, euroc_rig, read_sensor_yaml
from gslam_jax.datasets.reading import read_image
from gslam_jax.vo.calib import CalibrationError
from gslam_jax.vo.frontend import FrontEndParams
from gslam_jax.vo.geometry import invert, rotation_angle

SRC = Path(__file__).resolve().parents[2] / "shared" / "data" / "euroc-v1_01-static-20"


@pytest.fixture(scope="module")
def mav() -> Path:
    if not (SRC / "mav0").is_dir():
        pytest.skip(f"real EuRoC frames not found at {SRC} (see shared/data/README.md)")
    cv2.setNumThreads(1)
    return SRC / "mav0"


def _median_dy(left: np.ndarray, right: np.ndarray) -> tuple[float, float, int]:
    """Row offset of ORB matches (an independent detector/matcher from the VO's)."""
    orb = cv2.ORB_create(2000)
    kl, dl = orb.detectAndCompute(left, None)
    kr, dr = orb.detectAndCompute(right, None)
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(dl, dr)
    pl = np.array([kl[m.queryIdx].pt for m in matches])
    pr = np.array([kr[m.trainIdx].pt for m in matches])
    dx, dy = pl[:, 0] - pr[:, 0], pl[:, 1] - pr[:, 1]
    keep = (dx > 0) & (dx < 100) & (np.abs(dy) < 20)  # plausible stereo matches only
    return float(np.median(np.abs(dy[keep]))), float(np.mean(np.abs(dy[keep]) <= 1.0)), int(keep.sum())


def test_rectification_puts_matches_on_the_same_row(mav: Path):
    rig = euroc_rig(read_sensor_yaml(mav / "cam0" / "sensor.yaml"),
                    read_sensor_yaml(mav / "cam1" / "sensor.yaml"))
    name = sorted((mav / "cam0" / "data").glob("*.png"))[0].name
    raw = read_image(mav / "cam0" / "data" / name), read_image(mav / "cam1" / "data" / name)
    dy_raw, _, _ = _median_dy(*raw)
    dy, dy_mean, n = _median_dy(*rig.rectify(*raw))
    print(f"\nEuRoC vertical disparity: raw median {dy_raw:.2f} px, rectified median {dy:.2f} px, "
          f"{100 * dy_mean:.0f}% within 1 px ({n} ORB matches)")
    assert dy_mean > 0.8
    assert n > 100
    assert dy < 0.5
    assert dy_raw > 2 * dy  # the check can tell rectified from raw images
    assert 0.10 < rig.baseline < 0.12  # EuRoC's stereo baseline is about 11 cm


def test_static_vo_does_not_invent_motion(mav: Path):
    res = euroc_frontend(SRC, EurocParams(frontend=FrontEndParams(dense=False)))
    rel = invert(res.poses[0]) @ res.poses[-1]
    move, turn = np.linalg.norm(rel[:3, 3]), np.degrees(rotation_angle(rel))
    print(f"\nEuRoC 20 static frames: VO moved {100 * move:.2f} cm, {turn:.3f} deg")
    assert res.run.num_frames == 20 and res.summary.vo_failures == 0
    assert move < 0.02 and turn < 0.2
    gt = res.run.ground_truth
    assert np.abs(gt[-1] - gt[0]).max() < 0.02  # the ground truth agrees it stood still


def test_points_are_gravity_aligned(mav: Path):
    res = euroc_frontend(SRC, EurocParams(max_frames=2))
    m = res.run.local_maps[0]
    n = m[..., 0]
    heights = m[..., 1][n > 0] / n[n > 0]
    # The floor of the Vicon room lies at z = 0 of the robot frame (origin on the ground).
    assert abs(np.percentile(heights, 5)) < 0.15
    assert res.summary.tilt_corrections == 2


def test_sensor_yaml_missing_field_is_named(mav: Path, tmp_path: Path):
    text = (mav / "cam0" / "sensor.yaml").read_text()
    bad = tmp_path / "sensor.yaml"
    bad.write_text("\n".join(l for l in text.splitlines() if not l.startswith("intrinsics")))
    with pytest.raises(CalibrationError, match=r"sensor.yaml: missing field 'intrinsics'"):
        read_sensor_yaml(bad)
