"""KITTI adapter on real frames, and its handling of bad input (named errors or counted fallback)."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from gslam_jax.datasets.kitti import KittiParams, kitti_frontend
from gslam_jax.vo.calib import CalibrationError, ImageError
from gslam_jax.vo.frontend import FrontEndParams

SRC = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti-stereo-51"


@pytest.fixture()
def small_seq(tmp_path: Path) -> Path:
    """The first 5 frames copied into a writable KITTI layout."""
    if not (SRC / "sequences" / "seq1").is_dir():
        pytest.skip(f"real KITTI frames not found at {SRC} (see shared/data/README.md)")
    cv2.setNumThreads(1)
    seq = tmp_path / "sequences" / "seq1"
    for cam in ("image_0", "image_1"):
        (seq / cam).mkdir(parents=True)
        for t in range(5):
            shutil.copy(SRC / "sequences" / "seq1" / cam / f"{t:06d}.png", seq / cam)
    shutil.copy(SRC / "sequences" / "seq1" / "calib.txt", seq)
    (tmp_path / "poses").mkdir()
    lines = (SRC / "poses" / "seq1.txt").read_text().splitlines()[:5]
    (tmp_path / "poses" / "seq1.txt").write_text("\n".join(lines) + "\n")
    return tmp_path


def _vo_only(**kw) -> KittiParams:
    return KittiParams(frontend=FrontEndParams(dense=False, **kw))


def test_adapter_builds_a_run_with_ground_level_maps(small_seq: Path):
    # 64 disparities (the generic default) reach down to 5.9 m only on KITTI's rig: it says so.
    with pytest.warns(UserWarning, match=r"64 disparities covers depths from 5\.9 m"):
        res = kitti_frontend(small_seq, KittiParams(frontend=FrontEndParams(stereo=_fast_stereo())))
    run = res.run
    assert run.num_frames == 5 and not run.vo_failed.any()
    assert run.num_local_maps >= 1 and run.obs_index[0] == 0
    # Straight drive: VO path agrees with the projected ground truth to a few cm over ~5 m.
    vo, gt = run.vo_poses(), run.ground_truth
    assert gt[-1, 0] > 4.0 and abs(gt[-1, 1]) < 0.2
    assert np.abs(vo[:, :2] - gt[:, :2]).max() < 0.1
    # Robot frame: the road under the car is near z = 0 (camera 1.65 m up, x forward).
    m = run.local_maps[0]
    n = m[..., 0]
    heights = m[..., 1][n > 0] / n[n > 0]
    assert abs(np.percentile(heights, 10)) < 0.3
    ahead = n[run.local_maps.shape[1] // 2 + 10:, :].sum()
    behind = n[:run.local_maps.shape[1] // 2 - 10, :].sum()
    assert ahead > 10 * max(behind, 1)


def _fast_stereo():
    from gslam_jax.vo.stereo import DenseStereoParams
    return DenseStereoParams(stride=4)


def test_missing_image_is_named_or_counted(small_seq: Path):
    missing = small_seq / "sequences" / "seq1" / "image_1" / "000002.png"
    missing.unlink()
    with pytest.raises(ImageError, match="000002.png"):
        kitti_frontend(small_seq, _vo_only())
    res = kitti_frontend(small_seq, _vo_only(on_bad_frame="fallback"))
    assert [t for t, _ in res.summary.bad_frames] == [2]
    assert "000002.png" in res.summary.text()
    assert res.run.vo_failed.tolist() == [False, False, True, True, False]
    assert res.summary.sources["hold"] == 2
    np.testing.assert_allclose(res.run.controls[2], res.run.controls[1])  # constant velocity


def test_corrupt_image_is_named(small_seq: Path):
    bad = small_seq / "sequences" / "seq1" / "image_0" / "000003.png"
    bad.write_bytes(b"not a png at all")
    with pytest.raises(ImageError, match="000003.png.*corrupt"):
        kitti_frontend(small_seq, _vo_only())


def test_blank_frame_falls_back_and_is_counted(small_seq: Path):
    for cam in ("image_0", "image_1"):
        cv2.imwrite(str(small_seq / "sequences" / "seq1" / cam / "000002.png"),
                    np.full((370, 1226), 128, np.uint8))
    res = kitti_frontend(small_seq, _vo_only())
    assert res.run.vo_failed.tolist() == [False, False, True, True, False]
    assert res.summary.failures["too few features"] == [2, 3]
    assert res.summary.vo_failures == 2


def test_mismatched_sizes_are_named(small_seq: Path):
    right = small_seq / "sequences" / "seq1" / "image_1" / "000001.png"
    cv2.imwrite(str(right), cv2.imread(str(right), cv2.IMREAD_GRAYSCALE)[:, :1000])
    with pytest.raises(ImageError, match=r"frame 1: right image is 1000x370"):
        kitti_frontend(small_seq, _vo_only())


def test_calibration_missing_field_is_named(small_seq: Path):
    calib = small_seq / "sequences" / "seq1" / "calib.txt"
    calib.write_text(calib.read_text().splitlines()[0] + "\n")
    with pytest.raises(CalibrationError, match=r"calib.txt: missing field 'P1'"):
        kitti_frontend(small_seq, _vo_only())
