"""RectifiedRig.from_rectification (per-camera K, D, R, P as ROS CameraInfo gives them) against
OpenCV's own projection of known 3D points."""

import cv2
import numpy as np
import pytest

from gslam_jax.vo.calib import CalibrationError, CameraModel, RectifiedRig

SIZE = (320, 240)
K0 = np.array([[300.0, 0, 158], [0, 302, 121], [0, 0, 1]])
K1 = np.array([[305.0, 0, 162], [0, 301, 118], [0, 0, 1]])
D0 = np.array([-0.12, 0.03, 1e-3, -5e-4, 0.0])
D1 = np.array([-0.10, 0.02, -1e-3, 4e-4, 0.0])
R10 = cv2.Rodrigues(np.array([0.01, -0.02, 0.005]))[0]
T10 = np.array([-0.12, 0.003, 0.002])  # camera 1 to the right of camera 0


def _cameras(model: str = "plumb_bob", d0=D0, d1=D1):
    r0, r1, p0, p1, *_ = cv2.stereoRectify(K0, d0, K1, d1, SIZE, R10, T10.reshape(3, 1),
                                           flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.0)
    return (CameraModel(K0, d0, r0, p0, SIZE, model), CameraModel(K1, d1, r1, p1, SIZE, model))


def test_remap_tables_send_rectified_pixels_to_opencv_raw_projections():
    left, right = _cameras()
    rig = RectifiedRig.from_rectification(left, right, "test.yaml")
    lx, ly, rx, ry = rig.maps
    rng = np.random.default_rng(0)
    for _ in range(20):
        iu, iv = int(rng.integers(60, 260)), int(rng.integers(50, 190))
        z = rng.uniform(2.0, 10.0)
        # The point seen at rectified pixel (iu, iv) of the left camera at depth z.
        x_rect = np.array([(iu - rig.cx) / rig.fx * z, (iv - rig.cy) / rig.fy * z, z])
        raw0 = cv2.projectPoints((left.r.T @ x_rect)[None], np.zeros(3), np.zeros(3), K0,
                                 D0)[0].ravel()
        assert np.allclose([lx[iv, iu], ly[iv, iu]], raw0, atol=0.05)
        # The same point in the right camera: same row, disparity fx * b / z.
        x1 = R10 @ (left.r.T @ x_rect) + T10
        raw1 = cv2.projectPoints(x1[None], np.zeros(3), np.zeros(3), K1, D1)[0].ravel()
        ur = iu - rig.fx * rig.baseline / z
        col = int(np.floor(ur))
        frac = ur - col  # the table is linear between pixels to well under 0.05 px here
        got = (1 - frac) * np.array([rx[iv, col], ry[iv, col]]) + frac * np.array(
            [rx[iv, col + 1], ry[iv, col + 1]])
        assert np.allclose(got, raw1, atol=0.05)
    assert rig.baseline == pytest.approx(np.linalg.norm(T10), rel=1e-6)


def test_agrees_with_from_raw():
    left, right = _cameras()
    a = RectifiedRig.from_rectification(left, right)
    b = RectifiedRig.from_raw(K0, D0, K1, D1, R10, T10, SIZE)
    assert (a.fx, a.fy, a.cx, a.cy) == pytest.approx((b.fx, b.fy, b.cx, b.cy))
    assert a.baseline == pytest.approx(b.baseline)
    for m, n in zip(a.maps, b.maps):
        assert np.allclose(m, n, atol=1e-3)


def test_prerectified_cameras_need_no_remap():
    p0 = np.array([[300.0, 0, 160, 0], [0, 300, 120, 0], [0, 0, 1, 0]])
    p1 = p0.copy()
    p1[0, 3] = -300.0 * 0.5
    k = p0[:, :3]
    rig = RectifiedRig.from_rectification(CameraModel(k, np.zeros(5), np.eye(3), p0, SIZE),
                                          CameraModel(k, np.zeros(5), np.eye(3), p1, SIZE))
    assert rig.maps is None and rig.baseline == pytest.approx(0.5)


def test_fisheye_tables_match_opencv_fisheye_projection():
    d = np.array([0.05, -0.01, 0.002, -0.0005])
    left, right = _cameras("equidistant", np.zeros(5), np.zeros(5))
    left = CameraModel(K0, d, left.r, left.p, SIZE, "equidistant")
    right = CameraModel(K1, d, right.r, right.p, SIZE, "equidistant")
    rig = RectifiedRig.from_rectification(left, right)
    lx, ly = rig.maps[:2]
    iu, iv, z = 200, 150, 5.0
    x_rect = np.array([(iu - rig.cx) / rig.fx * z, (iv - rig.cy) / rig.fy * z, z])
    raw = cv2.fisheye.projectPoints((left.r.T @ x_rect).reshape(1, 1, 3), np.zeros(3),
                                    np.zeros(3), K0, d)[0].ravel()
    assert np.allclose([lx[iv, iu], ly[iv, iu]], raw, atol=0.05)


@pytest.mark.parametrize("change, field", [
    (dict(k=np.eye(2)), "'K'"), (dict(p=np.zeros((3, 3))), "'P'"),
    (dict(r=2 * np.eye(3)), "'R'"), (dict(d=np.ones(3)), "'D'"),
    (dict(distortion_model="kannala"), "distortion_model"),
    (dict(d=np.array([np.nan, 0, 0, 0, 0])), "'D'")])
def test_bad_fields_are_named(change, field):
    left, right = _cameras()
    bad = CameraModel(**{**left.__dict__, **change})
    with pytest.raises(CalibrationError, match=f"cam.yaml: left.*{field}"):
        RectifiedRig.from_rectification(bad, right, "cam.yaml")
