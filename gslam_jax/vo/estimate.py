"""Frame-to-frame motion from inlier matches (Howard 2008 sec. 3.4; paper section 4 step 4).

The motion T_ab (X_a = R X_b + t) minimises the reprojection error of the inliers in both frames,
in (u, v, disparity) image coordinates, by Levenberg-Marquardt started from the closed-form
least-squares rigid fit of the 3-D points (Arun/Kabsch), so no prior motion estimate is needed.
Matches whose error stays above a gate are dropped and the fit repeated (Howard's validation).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from gslam_jax.vo.geometry import make_transform, matrix_to_rotvec, rotvec_to_matrix

__all__ = ["Camera", "MotionEstimate", "project", "triangulate", "rigid_fit", "estimate_motion"]


class Camera(NamedTuple):
    """Rectified stereo camera: focal lengths, principal point, baseline (metres)."""

    fx: float
    fy: float
    cx: float
    cy: float
    baseline: float


class MotionEstimate(NamedTuple):
    """Result of :func:`estimate_motion`.

    transform: 4x4 T_ab; covariance: [6, 6] of (rotation vector, translation), scaled by the
    residual variance; rms: reprojection RMS over inliers, pixels; inliers: indices kept;
    condition: condition number of J^T J (degenerate geometry shows up as a huge value).
    """

    transform: np.ndarray
    covariance: np.ndarray
    rms: float
    inliers: np.ndarray
    condition: float


def project(cam: Camera, x: np.ndarray) -> np.ndarray:
    """[..., 3] camera points -> [..., 3] (u, v, disparity)."""
    z = x[..., 2]
    return np.stack([cam.fx * x[..., 0] / z + cam.cx, cam.fy * x[..., 1] / z + cam.cy,
                     cam.fx * cam.baseline / z], axis=-1)


def triangulate(cam: Camera, j: np.ndarray) -> np.ndarray:
    """[N, 3] (u, v, disparity) -> [N, 3] camera points (inverse of :func:`project`)."""
    z = cam.fx * cam.baseline / j[:, 2]
    return np.stack([(j[:, 0] - cam.cx) * z / cam.fx, (j[:, 1] - cam.cy) * z / cam.fy, z], axis=1)


def rigid_fit(pa: np.ndarray, pb: np.ndarray) -> np.ndarray:
    """Least-squares T_ab with pa ≈ R pb + t (Arun et al. 1987, SVD with reflection guard)."""
    ca, cb = pa.mean(0), pb.mean(0)
    u, _, vt = np.linalg.svd((pb - cb).T @ (pa - ca))
    s = np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))])
    r = vt.T @ s @ u.T
    return make_transform(r, ca - r @ cb)


def _rotations(w: np.ndarray) -> np.ndarray:
    """Rodrigues' formula for a batch of rotation vectors [P, 3] -> [P, 3, 3]."""
    theta = np.linalg.norm(w, axis=1)
    small = theta < 1e-12
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0, np.sin(safe) / safe)                 # sin(theta) / theta
    b = np.where(small, 0.0, (1.0 - np.cos(safe)) / safe ** 2)    # (1 - cos(theta)) / theta^2
    k = np.zeros((len(w), 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    k[:, 1, 0], k[:, 2, 0], k[:, 2, 1] = w[:, 2], -w[:, 1], w[:, 0]
    return np.eye(3) + a[:, None, None] * k + b[:, None, None] * (k @ k)


def _residuals(params: np.ndarray, cam: Camera, ja: np.ndarray, jb: np.ndarray,
               wa: np.ndarray, wb: np.ndarray) -> np.ndarray:
    """Reprojection residuals [P, N, 6] for P motions ``params`` [P, 6] (rotvec, t) at once:
    frame-b points moved into a against ja, frame-a points moved into b against jb."""
    r = _rotations(params[:, :3])
    t = params[:, None, 3:]
    ea = ja - project(cam, np.einsum("nj,pij->pni", wb, r) + t)
    eb = jb - project(cam, np.einsum("pnj,pji->pni", wa - t, r))
    return np.concatenate([ea, eb], axis=-1)


def _lm(params: np.ndarray, cam: Camera, ja, jb, wa, wb, iters: int
        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    lam = 1e-3
    res = _residuals(params[None], cam, ja, jb, wa, wb)[0].ravel()
    cost = res @ res
    steps = 1e-6 * np.eye(6)
    for _ in range(iters):
        # Forward differences: the 6 perturbed residual sets in one batched evaluation.
        perturbed = _residuals(params + steps, cam, ja, jb, wa, wb).reshape(6, -1)
        jac = ((perturbed - res) / 1e-6).T
        jtj, jtr = jac.T @ jac, jac.T @ res
        improved = False
        while lam < 1e8:
            delta = np.linalg.solve(jtj + lam * np.diag(np.diag(jtj) + 1e-12), -jtr)
            trial = params + delta
            r_trial = _residuals(trial[None], cam, ja, jb, wa, wb)[0].ravel()
            c_trial = r_trial @ r_trial
            if c_trial < cost:
                params, res, lam, improved = trial, r_trial, max(lam / 10, 1e-9), True
                converged = cost - c_trial < 1e-10 * max(cost, 1e-12)
                cost = c_trial
                break
            lam *= 10
        if not improved or converged:
            break
    return params, res.reshape(-1, 6), jac


def estimate_motion(cam: Camera, ja: np.ndarray, jb: np.ndarray, gate_px: float = 1.5,
                    iters: int = 20) -> MotionEstimate:
    """Motion T_ab from matched (u, v, d) observations ``ja`` [N, 3] and ``jb`` [N, 3].

    Requires N >= 3. Inliers are re-selected once: matches whose largest reprojection residual
    exceeds ``gate_px`` are dropped and the fit repeated on the rest (unless fewer than 3 would
    remain). The returned inliers are the matches of the final fit.
    """
    if len(ja) < 3:
        raise ValueError(f"need at least 3 matches to estimate motion, got {len(ja)}")
    wa, wb = triangulate(cam, ja), triangulate(cam, jb)
    t0 = rigid_fit(wa, wb)
    params = np.concatenate([matrix_to_rotvec(t0[:3, :3]), t0[:3, 3]])
    keep = np.arange(len(ja))
    params, res, jac = _lm(params, cam, ja, jb, wa, wb, iters)
    good = np.abs(res).max(axis=1) <= gate_px
    if not good.all() and good.sum() >= 3:
        keep = keep[good]
        params, res, jac = _lm(params, cam, ja[keep], jb[keep], wa[keep], wb[keep], iters)
    dof = max(res.size - 6, 1)
    sigma2 = float(res.ravel() @ res.ravel()) / dof
    jtj = jac.T @ jac
    eig = np.linalg.eigvalsh(jtj)
    with np.errstate(over="ignore"):  # absurd geometry (a km-scale baseline): cond = inf
        cond = float(eig[-1] / max(eig[0], 1e-300))
    # Each measurement enters two residuals (directly, and through its triangulated point in the
    # other frame), so J^T J counts the information twice: hence the factor 2.
    cov = 2.0 * np.linalg.pinv(jtj) * sigma2
    rms = float(np.sqrt(np.mean(res[:, [0, 1, 3, 4]] ** 2)))
    return MotionEstimate(make_transform(rotvec_to_matrix(params[:3]), params[3:]), cov, rms,
                          keep, cond)
