"""Stereo visual odometry, frame to frame (paper section 4; Howard 2008).

For each rectified stereo frame: corners with stereo range (step 1), SAD matches with the previous
frame (step 2), the rigidity clique of inliers (step 3), and the motion minimising inlier
reprojection error (step 4). A frame is declared a VO failure, with a reason, when it has too few
features, matches or inliers, when the geometry is degenerate, or when the fit is poor; the
caller then falls back to wheel/IMU increments (see :mod:`gslam_jax.vo.fallback`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from gslam_jax.vo.clique import rigid_inliers
from gslam_jax.vo.estimate import Camera, estimate_motion, triangulate
from gslam_jax.vo.features import (FeatureParams, Features, dense_feature_disparity, describe, detect,
                       feature_disparity, match_sad, prefilter, refine_matches)

__all__ = ["VOParams", "VOResult", "StereoVO"]


@dataclass(frozen=True)
class VOParams:
    """VO settings.

    clique_abs: rigidity tolerance in metres; clique_disp_px: disparity error (pixels) turned
    into an extra depth tolerance z^2/(f b) * px per point; max_depth_baselines: points farther
    than this many baselines are not used (their range is too poor); min_inliers: fewer inlier
    matches is a failure; max_rms_px: a poorer fit is a failure; max_condition: a worse
    conditioned J^T J is degenerate geometry; max_step_m / max_step_rad: larger frame-to-frame
    motions are rejected as implausible. disparity: where feature disparities come from when
    :meth:`StereoVO.step` is given the dense disparity map: "dense" reads them from it (paper
    sec. 4, no extra matching), "lk" always runs sparse LK stereo; without a map LK is used.
    """

    features: FeatureParams = field(default_factory=FeatureParams)
    clique_abs: float = 0.05
    clique_disp_px: float = 0.5
    max_depth_baselines: float = 60.0
    min_inliers: int = 12
    max_rms_px: float = 1.0
    max_condition: float = 1e10
    gate_px: float = 1.5
    max_step_m: float = 5.0
    max_step_rad: float = 0.5
    disparity: str = "dense"

    def __post_init__(self) -> None:
        if self.disparity not in ("dense", "lk"):
            raise ValueError(f"VOParams.disparity must be 'dense' or 'lk', got {self.disparity!r}")


class VOResult(NamedTuple):
    """One frame's VO outcome; ``transform`` is T_prev_cur (4x4, camera frames) when ok."""

    ok: bool
    transform: np.ndarray
    reason: str
    n_features: int
    n_matches: int
    n_inliers: int
    rms: float
    covariance: np.ndarray


def _fail(reason: str, nf: int = 0, nm: int = 0, ni: int = 0, rms: float = np.nan) -> VOResult:
    return VOResult(False, np.eye(4), reason, nf, nm, ni, rms, np.full((6, 6), np.nan))


class _Frame(NamedTuple):
    img: np.ndarray
    right: np.ndarray
    feats: Features
    disparity: np.ndarray | None


class StereoVO:
    """Frame-to-frame stereo VO; call :meth:`step` with each rectified pair in order.

    Holds only the previous frame. The first frame (and the frame after a gap, see
    :meth:`reset`) returns ``ok=False`` with reason ``"first frame"``.
    """

    def __init__(self, cam: Camera, params: VOParams = VOParams()):
        self.cam, self.params = cam, params
        self._prev: _Frame | None = None

    def reset(self) -> None:
        self._prev = None

    def _disparity(self, left: np.ndarray, right: np.ndarray, dense: np.ndarray | None,
                   uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        fp = self.params.features
        if dense is not None and self.params.disparity == "dense":
            return dense_feature_disparity(dense, uv, fp)
        return feature_disparity(left, right, uv, fp)

    def _features(self, left: np.ndarray, right: np.ndarray,
                  dense: np.ndarray | None = None) -> Features:
        fp = self.params.features
        uv = detect(left, fp)
        disp, ok = self._disparity(left, right, dense, uv)
        max_depth = self.params.max_depth_baselines * self.cam.baseline
        ok &= self.cam.fx * self.cam.baseline / np.maximum(disp, 1e-9) <= max_depth
        uv, disp = uv[ok], disp[ok]
        return Features(uv, disp, describe(prefilter(left), uv, fp.window))

    def step(self, left: np.ndarray, right: np.ndarray,
             disparity: np.ndarray | None = None) -> VOResult:
        """Process the next rectified grey pair; returns the motion from the previous frame.

        ``disparity``: the pair's dense disparity map (px, NaN invalid), if already computed.
        """
        feats = self._features(left, right, disparity)
        prev, self._prev = self._prev, _Frame(left, right, feats, disparity)
        if prev is None:
            return _fail("first frame", len(feats.uv))
        return self._motion(prev, self._prev)

    def _motion(self, a: _Frame, b: _Frame) -> VOResult:
        p, fp, cam = self.params, self.params.features, self.cam
        nf = min(len(a.feats.uv), len(b.feats.uv))
        if nf < p.min_inliers:
            return _fail("too few features", nf)
        radius = fp.search_radius * a.img.shape[1]
        pairs = match_sad(a.feats, b.feats, radius, fp.max_sad)
        if len(pairs) < p.min_inliers:
            return _fail("too few matches", nf, len(pairs))
        ia, ib = pairs[:, 0], pairs[:, 1]
        uv_b, ok = refine_matches(a.img, b.img, a.feats.uv[ia], b.feats.uv[ib], fp.window)
        disp_b, ok_d = self._disparity(b.img, b.right, b.disparity, uv_b)
        ok &= ok_d
        ia, uv_b, disp_b = ia[ok], uv_b[ok], disp_b[ok]
        ja = np.column_stack([a.feats.uv[ia], a.feats.disparity[ia]]).astype(np.float64)
        jb = np.column_stack([uv_b, disp_b]).astype(np.float64)
        nm = len(ja)
        if nm < p.min_inliers:
            return _fail("too few matches", nf, nm)
        wa, wb = triangulate(cam, ja), triangulate(cam, jb)
        z = np.maximum(wa[:, 2], wb[:, 2])
        tol = 0.5 * p.clique_abs + z * z / (cam.fx * cam.baseline) * p.clique_disp_px
        inl = rigid_inliers(wa, wb, tol)
        if len(inl) < p.min_inliers:
            return _fail("too few inliers", nf, nm, len(inl))
        est = estimate_motion(cam, ja[inl], jb[inl], p.gate_px)
        ni = len(est.inliers)
        if ni < p.min_inliers:
            return _fail("too few inliers", nf, nm, ni, est.rms)
        if not np.isfinite(est.condition) or est.condition > p.max_condition:
            return _fail("degenerate geometry", nf, nm, ni, est.rms)
        if est.rms > p.max_rms_px:
            return _fail("poor fit", nf, nm, ni, est.rms)
        t = est.transform
        angle = np.arccos(np.clip((np.trace(t[:3, :3]) - 1) / 2, -1, 1))
        if np.linalg.norm(t[:3, 3]) > p.max_step_m or angle > p.max_step_rad:
            return _fail("implausible motion", nf, nm, ni, est.rms)
        return VOResult(True, t, "ok", nf, nm, ni, est.rms, est.covariance)
