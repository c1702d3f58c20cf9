"""Motion estimation: closed-form rigid fit and LM on reprojection error, against SciPy."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from gslam_jax.vo.estimate import Camera, estimate_motion, project, rigid_fit, triangulate
from gslam_jax.vo.geometry import increments_2d, matrix_to_rotvec, rotvec_to_matrix

CAM = Camera(700.0, 700.0, 600.0, 180.0, 0.54)


def test_rotvec_matches_scipy():
    rng = np.random.default_rng(0)
    for w in rng.normal(scale=0.8, size=(20, 3)):
        np.testing.assert_allclose(rotvec_to_matrix(w), Rotation.from_rotvec(w).as_matrix(),
                                   atol=1e-12)
        np.testing.assert_allclose(matrix_to_rotvec(rotvec_to_matrix(w)), w, atol=1e-9)


def test_project_triangulate_roundtrip():
    x = np.array([[1.0, -0.5, 8.0], [-3.0, 1.0, 20.0]])
    np.testing.assert_allclose(triangulate(CAM, project(CAM, x)), x, atol=1e-12)


def test_rigid_fit_matches_scipy_alignment():
    rng = np.random.default_rng(1)
    pb = rng.normal(size=(30, 3)) * 5
    rot = Rotation.from_rotvec([0.1, -0.3, 0.2])
    pa = rot.apply(pb) + [1.0, 2.0, 3.0] + rng.normal(scale=0.01, size=pb.shape)
    t = rigid_fit(pa, pb)
    ref, _ = Rotation.align_vectors(pa - pa.mean(0), pb - pb.mean(0))
    np.testing.assert_allclose(t[:3, :3], ref.as_matrix(), atol=1e-9)


def test_lm_recovers_motion_and_covariance_is_calibrated():
    rng = np.random.default_rng(2)
    rot = Rotation.from_euler("xyz", [0.5, 3.0, 0.2], degrees=True)
    t = np.array([0.05, 0.02, 1.2])
    wb = np.column_stack([rng.uniform(-8, 8, 150), rng.uniform(-1, 2, 150), rng.uniform(4, 30, 150)])
    wa = rot.apply(wb) + t
    errs = []
    for _ in range(30):
        ja = project(CAM, wa) + rng.normal(scale=0.3, size=wa.shape)
        jb = project(CAM, wb) + rng.normal(scale=0.3, size=wb.shape)
        est = estimate_motion(CAM, ja, jb, gate_px=10.0)
        errs.append(est.transform[:3, 3] - t)
        assert est.rms < 0.7  # both frames noisy: ~0.3 * sqrt(2) per coordinate
    errs = np.array(errs)
    assert np.linalg.norm(errs.mean(0)) < 0.02
    # Reported translation std agrees with the spread over repeats (approximate: within 2x).
    reported = np.sqrt(np.diag(est.covariance)[3:])
    ratio = errs.std(0) / reported
    assert np.all((ratio > 0.5) & (ratio < 2.0)), ratio


def test_inliers_are_the_matches_of_the_final_fit():
    """Outliers are dropped once and the fit repeated; the inliers returned are the matches that
    fit used, so refitting them alone (no gate) gives the same motion and residual."""
    rng = np.random.default_rng(3)
    rot = Rotation.from_euler("xyz", [0.2, 2.0, 0.1], degrees=True)
    t = np.array([0.02, 0.01, 0.8])
    wb = np.column_stack([rng.uniform(-8, 8, 60), rng.uniform(-1, 2, 60), rng.uniform(4, 25, 60)])
    wa = rot.apply(wb) + t
    ja = project(CAM, wa) + rng.normal(scale=0.2, size=wa.shape)
    jb = project(CAM, wb) + rng.normal(scale=0.2, size=wb.shape)
    ja[:8, 0] += 25.0                              # gross outliers
    ja[8:20, 0] += np.linspace(0.5, 2.5, 12)       # graded ones, some near the gate
    est = estimate_motion(CAM, ja, jb, gate_px=1.5)
    assert not np.isin(np.arange(8), est.inliers).any()
    again = estimate_motion(CAM, ja[est.inliers], jb[est.inliers], gate_px=1e9)
    np.testing.assert_allclose(again.transform, est.transform, atol=1e-9)
    np.testing.assert_allclose(again.rms, est.rms, rtol=1e-9)


def test_increments_2d_integrate_back():
    from gslam_jax.run import integrate_controls
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 0.2, 0.3], [1.5, 1.0, 1.2], [1.0, 2.0, 3.0]])
    u = increments_2d(poses)
    out = integrate_controls(u, poses[0])
    np.testing.assert_allclose(out[:, :2], poses[:, :2], atol=1e-12)
    np.testing.assert_allclose(np.angle(np.exp(1j * (out[:, 2] - poses[:, 2]))), 0, atol=1e-12)


def test_batched_rodrigues_matches_scipy():
    from gslam_jax.vo.estimate import _rotations

    rng = np.random.default_rng(3)
    w = np.concatenate([rng.normal(scale=0.7, size=(20, 3)), np.zeros((1, 3)), [[1e-14, 0, 0]]])
    np.testing.assert_allclose(_rotations(w), Rotation.from_rotvec(w).as_matrix(), atol=1e-12)
