"""The dense disparity's noise, measured from the run itself, and each point's depth error.

Without ground truth a disparity map can be checked against the previous frame's: a pixel
triangulated at frame t-1, moved by the VO's camera motion and projected into frame t, predicts
frame t's disparity there. The residuals hold both frames' matching errors (and the VO's, small
beside them), so a robust spread of the residuals over sqrt(2) estimates the disparity noise
sigma_d: the part of it that changes from frame to frame. An error that stays with the
texture escapes it (measured on rendered ground: docs/notebook/real-data.md, "Moved from code
comments").
It is kept per disparity band (``DISPARITY_EDGES``): matching degrades with range faster than
a constant sigma_d says where far surfaces lose their texture or are seen at a grazing angle
(docs/notebook/real-data.md, "The rendered maze: its far points").

A point's depth error then follows to first order, sigma_z = z^2 sigma_d(d) / (f b), and the
front-end keeps the points whose sigma_z is within ``[stereo] max_depth_error``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gslam_jax.vo.calib import RectifiedRig

__all__ = ["DISPARITY_EDGES", "temporal_residuals", "DisparityNoise", "depth_errors"]

# Disparity bands (px): half-octaves from 2 to 128 px; below 2 px and above 128 px join the end
# bands.
DISPARITY_EDGES = 2.0 ** np.arange(1.0, 7.01, 0.5)
_RESIDUAL_STEP = 0.02  # px: the resolution of the residual histograms
_RESIDUAL_BINS = 500   # |residual| up to 10 px; larger ones count in the last bin


def temporal_residuals(prev_disparity: np.ndarray, disparity: np.ndarray,
                       t_prev_cur: np.ndarray, rig: RectifiedRig, stride: int = 2,
                       max_disparity: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """(predicted disparity, residual) at every ``stride``-th valid pixel of
    ``prev_disparity`` that lands inside ``disparity`` where it is valid, with a predicted
    disparity under ``max_disparity`` (the matcher's search range: it cannot report more).

    The residual is measured minus predicted, scaled by sqrt(2 / (1 + J^2)) with J the
    prediction's gain on the previous frame's error (d d_pred / d d_prev = g z^2 / z_cur^2, g
    the depth axis's share of the ray): its spread is sqrt(2) sigma_d, as of two frames seen
    alike, however far the camera moved toward the point.

    ``t_prev_cur`` is the camera motion (4x4, the current camera frame in the previous one, as
    ``VOResult.transform``). Frame t's disparity is read bilinearly at the projected position;
    a NaN neighbour (no match) or the image's edge drops the pixel.
    A block matcher's errors are correlated over its window, so the bilinear read takes them
    whole; noise independent from pixel to pixel would be averaged by it, and its sigma
    under-estimated by up to 15 %.
    """
    fb = rig.fx * rig.baseline
    d = prev_disparity[::stride, ::stride]
    v, u = np.mgrid[0:prev_disparity.shape[0]:stride, 0:prev_disparity.shape[1]:stride]
    ok = np.isfinite(d) & (d > 0)
    d, u, v = d[ok].astype(np.float64), u[ok], v[ok]
    z = fb / d
    pts = np.stack([(u - rig.cx) * z / rig.fx, (v - rig.cy) * z / rig.fy, z], axis=1)
    r, t = t_prev_cur[:3, :3], t_prev_cur[:3, 3]
    cur = (pts - t) @ r  # R^T (p - t): the previous camera's points in the current frame
    ahead = cur[:, 2] > 1e-6
    cur, z, g = cur[ahead], z[ahead], (pts[ahead] / z[ahead, None]) @ r[:, 2]
    pu = rig.fx * cur[:, 0] / cur[:, 2] + rig.cx
    pv = rig.fy * cur[:, 1] / cur[:, 2] + rig.cy
    read = _bilinear(disparity, pu, pv)
    predicted = fb / cur[:, 2]
    gain = g * (z / cur[:, 2]) ** 2
    scale = np.sqrt(2.0 / (1.0 + gain * gain))
    valid = np.isfinite(read) & (predicted < max_disparity)
    return predicted[valid], scale[valid] * (read[valid] - predicted[valid])


def _bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``image`` at (column u, row v), bilinear; NaN outside or where a neighbour is NaN."""
    h, w = image.shape
    u0, v0 = np.floor(u), np.floor(v)
    inside = (u0 >= 0) & (v0 >= 0) & (u0 + 1 <= w - 1) & (v0 + 1 <= h - 1)
    out = np.full(u.shape, np.nan)
    i, j = v0[inside].astype(np.int64), u0[inside].astype(np.int64)
    a, b = v[inside] - i, u[inside] - j
    img = image.astype(np.float64, copy=False)
    out[inside] = ((1 - a) * ((1 - b) * img[i, j] + b * img[i, j + 1])
                   + a * ((1 - b) * img[i + 1, j] + b * img[i + 1, j + 1]))
    return out


@dataclass
class DisparityNoise:
    """A running estimate of sigma_d per disparity band, from temporal residuals.

    Each band keeps a histogram of |residual|, every earlier frame's counts multiplied by
    ``forget`` as a frame is added (about 1 / (1 - forget) frames remembered).
    ``sigma(d)`` is 1.4826 median|residual| / sqrt(2) (a Gaussian's sigma from its median
    absolute deviation, for the difference of two frames' errors) where a band holds at least
    ``min_samples`` (forgetting counted), and ``prior_std`` elsewhere.
    """

    prior_std: float = 0.25
    forget: float = 0.9
    min_samples: float = 100.0
    counts: np.ndarray = field(default_factory=lambda: np.zeros(
        (len(DISPARITY_EDGES) + 1, _RESIDUAL_BINS)))

    def update(self, predicted: np.ndarray, residual: np.ndarray) -> None:
        """Add one frame's residuals (``temporal_residuals``)."""
        self.counts *= self.forget
        band = np.searchsorted(DISPARITY_EDGES, predicted)
        cell = np.minimum((np.abs(residual) / _RESIDUAL_STEP).astype(np.int64),
                          _RESIDUAL_BINS - 1)
        np.add.at(self.counts, (band, cell), 1.0)

    def band_sigmas(self) -> np.ndarray:
        """sigma_d (px) of each band, ``prior_std`` where a band has too few samples."""
        total = self.counts.sum(axis=1)
        cum = np.cumsum(self.counts, axis=1)
        half = np.argmax(cum >= 0.5 * total[:, None], axis=1)  # the median's histogram bin
        below = np.where(half > 0, cum[np.arange(len(half)), half - 1], 0.0)
        inside = self.counts[np.arange(len(half)), half]
        frac = np.where(inside > 0, (0.5 * total - below) / np.maximum(inside, 1e-300), 0.5)
        median = (half + frac) * _RESIDUAL_STEP
        sigma = 1.4826 * median / np.sqrt(2.0)
        return np.where(total >= self.min_samples, sigma, self.prior_std)

    def text(self) -> str:
        """The measured bands, e.g. "4-5.7 px: 0.13" (empty when none is measured yet)."""
        edges = np.concatenate([[0.0], DISPARITY_EDGES, [np.inf]])
        measured = self.counts.sum(axis=1) >= self.min_samples
        return ", ".join(f"{edges[b]:.3g}-{edges[b + 1]:.3g} px: {s:.2f}"
                         for b, s in enumerate(self.band_sigmas()) if measured[b])

    def sigma(self, disparity: np.ndarray) -> np.ndarray:
        """sigma_d (px) for each disparity, by its band."""
        return self.band_sigmas()[np.searchsorted(DISPARITY_EDGES, disparity)]


def depth_errors(points_cam: np.ndarray, rig: RectifiedRig, noise: DisparityNoise
                 ) -> np.ndarray:
    """First-order depth error (m) of camera-frame points: z^2 sigma_d(d) / (f b), d = f b / z."""
    fb = rig.fx * rig.baseline
    z = np.asarray(points_cam, np.float64)[:, 2]
    return z * z * noise.sigma(fb / z) / fb
