"""Dense stereo: rectified pair -> disparity -> 3-D points (paper section 4 "stereo correlator").

The dense range data feeds the local maps (paper 6.3). Points are returned in the rectified left
camera frame; :func:`to_robot_frame` moves them into the gravity-aligned robot frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from gslam_jax.vo.calib import RectifiedRig

__all__ = ["DenseStereoParams", "NEAREST_DENSE_DEPTH", "disparities_from_depth",
           "with_calibrated_range", "dense_disparity", "drop_depth_edges", "disparity_to_points",
           "to_robot_frame"]

# The nearest depth (metres) a source's own dense search range covers: a surface nearer than
# fx * baseline / num_disparities is matched wrongly as a far point.
NEAREST_DENSE_DEPTH = 3.0


@dataclass(frozen=True)
class DenseStereoParams:
    """StereoSGBM settings (``algorithm="bm"`` picks the faster, noisier StereoBM).

    num_disparities: search range in pixels (multiple of 16; 0: from the calibration,
    :func:`with_calibrated_range`); block: matching window side;
    min_disparity_px: disparities below this (far points) are dropped; stride: keep every
    ``stride``-th pixel in each direction when making points.
    max_depth_error: metres; the front-end makes no point whose depth error, to first order in
    the disparity noise it measures (``vo.disparity_noise``), would exceed it; inf keeps all.
    disparity_std: the disparity noise (px) assumed until a disparity band has been measured.
    edge_ratio: the points of a pixel whose 5 x 5 neighbourhood spans more than this fraction of
    its disparity, or holds an unmatched pixel, are not made (``drop_depth_edges``); inf keeps
    them all.
    """

    algorithm: str = "sgbm"
    num_disparities: int = 64
    block: int = 5
    uniqueness: int = 10
    speckle_window: int = 100
    speckle_range: int = 2
    min_disparity_px: float = 1.0
    stride: int = 2
    max_depth_error: float = float("inf")
    disparity_std: float = 0.25
    edge_ratio: float = 0.5

    def matcher(self) -> cv2.StereoMatcher:
        if self.num_disparities % 16:
            raise ValueError(f"num_disparities must be a multiple of 16, got {self.num_disparities}")
        if self.algorithm == "bm":
            m = cv2.StereoBM_create(self.num_disparities, max(5, self.block | 1))
            m.setUniquenessRatio(self.uniqueness)
            m.setSpeckleWindowSize(self.speckle_window)
            m.setSpeckleRange(self.speckle_range)
            return m
        if self.algorithm != "sgbm":
            raise ValueError(f"unknown stereo algorithm {self.algorithm!r} (use 'sgbm' or 'bm')")
        area = self.block * self.block
        return cv2.StereoSGBM_create(
            minDisparity=0, numDisparities=self.num_disparities, blockSize=self.block,
            P1=8 * area, P2=32 * area, uniquenessRatio=self.uniqueness,
            speckleWindowSize=self.speckle_window, speckleRange=self.speckle_range,
            mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)


def disparities_from_depth(fx: float, baseline: float, nearest: float = NEAREST_DENSE_DEPTH,
                           at_least: int = 64) -> int:
    """The dense search range (pixels, a multiple of 16, at least ``at_least``) that matches
    surfaces from ``nearest`` metres on: a point at depth Z has disparity fx * baseline / Z."""
    need = fx * baseline / nearest
    return max(at_least, 16 * math.ceil(need / 16 - 1e-9))


def with_calibrated_range(params: DenseStereoParams, rig: RectifiedRig) -> DenseStereoParams:
    """``params`` with ``num_disparities`` 0 replaced by the calibration's
    (:func:`disparities_from_depth` of the rig's fx and baseline); any other value as given.
    Every source that leaves the range to the calibration searches the same range for the
    same rig (KITTI's fx * baseline of 380 px m: 128)."""
    if params.num_disparities:
        return params
    return replace(params, num_disparities=disparities_from_depth(rig.fx, rig.baseline))


def dense_disparity(left: np.ndarray, right: np.ndarray,
                    params: DenseStereoParams = DenseStereoParams(),
                    matcher: cv2.StereoMatcher | None = None) -> np.ndarray:
    """Disparity in pixels (float32), NaN where the matcher found none."""
    m = matcher if matcher is not None else params.matcher()
    raw = m.compute(left, right).astype(np.float32) / 16.0  # OpenCV returns fixed-point x16
    raw[raw < max(params.min_disparity_px, 1e-3)] = np.nan
    return raw


def drop_depth_edges(disparity: np.ndarray, ratio: float, window: int = 5) -> np.ndarray:
    """``disparity`` with NaN where the ``window`` x ``window`` neighbourhood's disparities span
    more than ``ratio`` times the pixel's own, or where it holds an unmatched (NaN) pixel.

    A block matcher's window straddles a depth edge and reports disparities between the near
    and the far surface there: points in the air between them (the "flying pixels" of depth
    cameras), which a height-variance map takes for tall structure.
    """
    if not np.isfinite(ratio):
        return disparity
    d = np.nan_to_num(disparity, nan=0.0).astype(np.float32)
    kernel = np.ones((window, window), np.uint8)
    spread = cv2.dilate(d, kernel) - cv2.erode(d, kernel, borderType=cv2.BORDER_REPLICATE)
    keep = (d > 0) & (spread <= ratio * d)
    return np.where(keep, disparity, np.nan).astype(disparity.dtype)


def disparity_to_points(disparity: np.ndarray, rig: RectifiedRig, stride: int = 1,
                        max_range: float = np.inf) -> np.ndarray:
    """Triangulate valid disparities into [N, 3] points in the rectified left camera frame."""
    d = disparity[::stride, ::stride]
    v, u = np.mgrid[0:disparity.shape[0]:stride, 0:disparity.shape[1]:stride]
    ok = np.isfinite(d) & (d > 0)
    d, u, v = d[ok].astype(np.float64), u[ok], v[ok]
    z = rig.fx * rig.baseline / d
    x = (u - rig.cx) * z / rig.fx
    y = (v - rig.cy) * z / rig.fy
    pts = np.stack([x, y, z], axis=1)
    return pts[z <= max_range]


def to_robot_frame(points_cam: np.ndarray, t_robot_cam: np.ndarray,
                   r_level: np.ndarray | None = None) -> np.ndarray:
    """Camera-frame points -> gravity-aligned robot frame.

    ``t_robot_cam`` is the 4x4 camera mount in the robot body frame (origin on the ground under
    the robot); ``r_level`` (3x3) removes the body's current roll and pitch (tilt correction).
    """
    r, t = t_robot_cam[:3, :3], t_robot_cam[:3, 3]
    if r_level is not None:
        r, t = r_level @ r, r_level @ t
    return points_cam @ r.T + t
