"""Stereo calibration and rectification (front-end step 1; paper section 4, Howard 2008 sec. 2).

A :class:`RectifiedRig` is what every later stage needs: one pinhole model (fx, fy, cx, cy) shared
by both rectified images, the baseline, and optionally the remap tables that take raw (distorted,
unrectified) images to rectified ones. KITTI ships rectified images (``from_projections``);
EuRoC ships raw images with a radial-tangential model (``from_raw``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from gslam_jax.errors import InputError

__all__ = ["CalibrationError", "RectifiedRig", "ImageError"]


class CalibrationError(InputError):
    """A calibration is missing a field or has an unusable value; the message names both."""


class ImageError(InputError):
    """An image is missing, unreadable or of the wrong size; the message names the file/frame."""


@dataclass(frozen=True)
class RectifiedRig:
    """Rectified stereo pair: left camera is the reference, right camera is at +baseline along x.

    ``r_left`` rotates raw-left-camera coordinates into the rectified left camera frame
    (identity for pre-rectified data), so extrinsics given for the raw camera can be carried over.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    baseline: float
    size: tuple[int, int]  # (width, height)
    r_left: np.ndarray = field(default_factory=lambda: np.eye(3))
    maps: tuple[np.ndarray, ...] | None = None  # (l_x, l_y, r_x, r_y) for cv2.remap

    @property
    def k(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @classmethod
    def from_projections(cls, p0: np.ndarray, p1: np.ndarray, size: tuple[int, int],
                         source: str = "<calibration>") -> "RectifiedRig":
        """From rectified 3x4 projection matrices (KITTI ``P0``, ``P1``)."""
        p0, p1 = np.asarray(p0, float).reshape(3, 4), np.asarray(p1, float).reshape(3, 4)
        if not np.allclose(p0[:, :3], p1[:, :3], rtol=1e-6, atol=1e-6):
            raise CalibrationError(f"{source}: P0 and P1 have different intrinsics; "
                                   "the images are not a rectified pair")
        fx = p0[0, 0]
        if not fx > 0:
            raise CalibrationError(f"{source}: field 'P0': focal length must be positive, got {fx}")
        baseline = (p0[0, 3] - p1[0, 3]) / fx
        if not baseline > 0:
            raise CalibrationError(f"{source}: field 'P1': baseline must be positive "
                                   f"(P1[0,3] = -fx * b), got b = {baseline}")
        return cls(fx=fx, fy=p0[1, 1], cx=p0[0, 2], cy=p0[1, 2], baseline=float(baseline),
                   size=(int(size[0]), int(size[1])))

    @classmethod
    def from_raw(cls, k0: np.ndarray, d0: np.ndarray, k1: np.ndarray, d1: np.ndarray,
                 r_10: np.ndarray, t_10: np.ndarray, size: tuple[int, int],
                 source: str = "<calibration>") -> "RectifiedRig":
        """From raw intrinsics/distortion and the pose of camera 0 in camera 1 (X_1 = R X_0 + t).

        Uses ``cv2.stereoRectify`` with alpha=0 (only valid pixels) and builds remap tables.
        CalibrationError (naming ``source``) for non-finite input, a non-positive focal length or
        image size, or a rig whose camera 1 is not to the right of camera 0 (baseline <= 0).
        """
        arrays = {"k0": k0, "d0": d0, "k1": k1, "d1": d1, "R": r_10, "t": t_10}
        for name, a in arrays.items():
            if not np.all(np.isfinite(np.asarray(a, float))):
                raise CalibrationError(f"{source}: {name} has a non-finite entry")
        for name, k in (("k0", k0), ("k1", k1)):
            k = np.asarray(k, float)
            if not (k[0, 0] > 0 and k[1, 1] > 0):
                raise CalibrationError(f"{source}: {name}: focal lengths must be positive, "
                                       f"got fx={k[0, 0]}, fy={k[1, 1]}")
        if not (int(size[0]) > 0 and int(size[1]) > 0):
            raise CalibrationError(f"{source}: image size must be positive, got {size}")
        size = (int(size[0]), int(size[1]))
        if not np.linalg.norm(np.asarray(t_10, float)) > 0:
            raise CalibrationError(f"{source}: the two cameras are at the same place (zero "
                                   "baseline: are cam0's and cam1's extrinsics the same?)")
        r0, r1, p0, p1, _, _, _ = cv2.stereoRectify(
            np.asarray(k0, float), np.asarray(d0, float), np.asarray(k1, float),
            np.asarray(d1, float), size, np.asarray(r_10, float),
            np.asarray(t_10, float).reshape(3, 1),
            flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.0)
        fx = p0[0, 0]
        if not (np.isfinite(fx) and fx > 0):
            raise CalibrationError(f"{source}: rectified focal length must be finite and "
                                   f"positive, got {fx}")
        baseline = float(-p1[0, 3] / fx)
        if not baseline > 0:
            raise CalibrationError(f"{source}: baseline must be positive, got {baseline:.4f} m "
                                   "(cam1 must be to the right of cam0; are they swapped?)")
        maps = (*cv2.initUndistortRectifyMap(k0, d0, r0, p0, size, cv2.CV_32FC1),
                *cv2.initUndistortRectifyMap(k1, d1, r1, p1, size, cv2.CV_32FC1))
        return cls(fx=fx, fy=p0[1, 1], cx=p0[0, 2], cy=p0[1, 2],
                   baseline=baseline, size=size, r_left=r0, maps=maps)

    def rectify(self, left: np.ndarray, right: np.ndarray,
                frame: str = "") -> tuple[np.ndarray, np.ndarray]:
        """Check sizes and remap a raw pair into the rectified geometry (no-op if pre-rectified)."""
        w, h = self.size
        for name, img in (("left", left), ("right", right)):
            if img.shape[:2] != (h, w):
                raise ImageError(f"{frame}: {name} image is {img.shape[1]}x{img.shape[0]}, "
                                 f"calibration expects {w}x{h}")
        if self.maps is None:
            return left, right
        lx, ly, rx, ry = self.maps
        return (cv2.remap(left, lx, ly, cv2.INTER_LINEAR),
                cv2.remap(right, rx, ry, cv2.INTER_LINEAR))
