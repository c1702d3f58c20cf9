"""Stereo calibration and rectification (front-end step 1; paper section 4, Howard 2008 sec. 2).

A :class:`RectifiedRig` is what every later stage needs: one pinhole model (fx, fy, cx, cy) shared
by both rectified images, the baseline, and optionally the remap tables that take raw (distorted,
unrectified) images to rectified ones. KITTI ships rectified images (``from_projections``);
EuRoC ships raw images with a radial-tangential model (``from_raw``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import cv2
import numpy as np

from gslam_jax.errors import InputError

__all__ = ["CalibrationError", "CameraModel", "RectifiedRig", "ImageError", "DISTORTION_MODELS"]

# ROS distortion_model names and how many coefficients D holds for each (None: any of 4, 5, 8,
# 12 or 14, as OpenCV reads them).
DISTORTION_MODELS = {"plumb_bob": None, "rational_polynomial": None, "equidistant": 4}


class CalibrationError(InputError):
    """A calibration is missing a field or has an unusable value; the message names both."""


class ImageError(InputError):
    """An image is missing, unreadable or of the wrong size; the message names the file/frame."""


@dataclass(frozen=True)
class CameraModel:
    """One camera of a stereo pair as ROS and OpenCV describe it: raw intrinsics ``k`` (3x3),
    distortion ``d``, the rectifying rotation ``r`` (3x3, raw camera to rectified) and the
    rectified projection ``p`` (3x4; the right camera's ``p[0, 3]`` is ``-fx * baseline``),
    for images of ``size`` (width, height)."""

    k: np.ndarray
    d: np.ndarray
    r: np.ndarray
    p: np.ndarray
    size: tuple[int, int]
    distortion_model: str = "plumb_bob"

    def check(self, where: str) -> None:
        """CalibrationError naming ``where`` and the field for a wrong shape or value."""
        shapes = {"K": (self.k, (3, 3)), "R": (self.r, (3, 3)), "P": (self.p, (3, 4))}
        for name, (a, shape) in shapes.items():
            a = np.asarray(a, float)
            if a.shape != shape:
                raise CalibrationError(f"{where}: field {name!r} must be {shape[0]}x{shape[1]}, "
                                       f"got shape {a.shape}")
            if not np.all(np.isfinite(a)):
                raise CalibrationError(f"{where}: field {name!r} has a non-finite entry")
        if self.distortion_model not in DISTORTION_MODELS:
            raise CalibrationError(f"{where}: distortion_model {self.distortion_model!r} is not "
                                   f"supported ({', '.join(DISTORTION_MODELS)})")
        d = np.asarray(self.d, float).ravel()
        wanted = DISTORTION_MODELS[self.distortion_model]
        allowed = (wanted,) if wanted else (0, 4, 5, 8, 12, 14)
        if d.size not in allowed and not (d.size and not d.any()):
            raise CalibrationError(f"{where}: field 'D' has {d.size} coefficients; "
                                   f"{self.distortion_model} takes "
                                   f"{' or '.join(map(str, allowed))}")
        if not np.all(np.isfinite(d)):
            raise CalibrationError(f"{where}: field 'D' has a non-finite entry")
        if not (np.asarray(self.k, float)[0, 0] > 0 and np.asarray(self.k, float)[1, 1] > 0):
            raise CalibrationError(f"{where}: field 'K': focal lengths must be positive")
        r = np.asarray(self.r, float)
        if not np.allclose(r @ r.T, np.eye(3), atol=1e-5) or np.linalg.det(r) < 0:
            raise CalibrationError(f"{where}: field 'R' is not a rotation (R R^T != I or det < 0)")
        if not (int(self.size[0]) > 0 and int(self.size[1]) > 0):
            raise CalibrationError(f"{where}: image size must be positive, got {self.size}")

    @property
    def rectified(self) -> bool:
        """The images are already rectified: no distortion and no rectifying rotation."""
        return (not np.asarray(self.d, float).any()
                and np.allclose(np.asarray(self.r, float), np.eye(3), atol=1e-9))

    def remap_tables(self) -> tuple[np.ndarray, np.ndarray]:
        """``cv2.remap`` tables (x, y) taking a raw image to the rectified one."""
        k, d = np.asarray(self.k, float), np.asarray(self.d, float).ravel()
        r, p = np.asarray(self.r, float), np.asarray(self.p, float)[:, :3]
        size = (int(self.size[0]), int(self.size[1]))
        if self.distortion_model == "equidistant":
            return cv2.fisheye.initUndistortRectifyMap(k, d.reshape(4, 1), r, p, size,
                                                       cv2.CV_32FC1)
        return cv2.initUndistortRectifyMap(k, d, r, p, size, cv2.CV_32FC1)


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

    @classmethod
    def from_rectification(cls, left: "CameraModel", right: "CameraModel",
                           source: str = "<calibration>") -> "RectifiedRig":
        """From each camera's raw intrinsics K, distortion D, rectifying rotation R and rectified
        projection P (ROS ``sensor_msgs/CameraInfo``, OpenCV/ROS calibration YAML).

        Images whose D is zero and R the identity are taken as already rectified (no remap);
        otherwise remap tables are built with ``cv2.initUndistortRectifyMap`` (radial-tangential
        models) or ``cv2.fisheye.initUndistortRectifyMap`` (``equidistant``). The baseline is
        ``-P_right[0, 3] / P_right[0, 0]`` (as :meth:`from_projections`).
        """
        if left.size != right.size:
            raise CalibrationError(f"{source}: the cameras' image sizes differ "
                                   f"({left.size} and {right.size})")
        for name, cam in (("left", left), ("right", right)):
            cam.check(f"{source}: {name}")
        rig = cls.from_projections(left.p, right.p, left.size, source)
        if all(cam.rectified for cam in (left, right)):
            return rig
        maps = (*left.remap_tables(), *right.remap_tables())
        return dataclasses.replace(rig, r_left=np.asarray(left.r, float), maps=maps)

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
