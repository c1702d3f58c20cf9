"""Corner features, their stereo range, and frame-to-frame SAD matching (Howard 2008, sec. 3.1-3.2).

Steps 1-2 of the paper's VO (section 4): detect corners in each frame, then match them between
frames by the sum of absolute differences (SAD) of pixel windows taken from a mean-removed
(high-pass) image, keeping mutually best pairs inside a search radius. The match position is then
refined to sub-pixel accuracy with one pyramid level of Lucas-Kanade seeded at the SAD match
(SAD gives the correspondence, LK only polishes it). Each feature's disparity is measured by
sparse stereo (pyramidal LK along the rectified row, checked forward-backward), which gives the
3-D position used by the rigidity test and the reprojection error.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

__all__ = ["FeatureParams", "Features", "detect", "feature_disparity", "dense_feature_disparity",
           "describe", "match_sad", "refine_matches", "prefilter"]


@dataclass(frozen=True)
class FeatureParams:
    """Detection and matching settings.

    fast_threshold: FAST corner threshold (20 finds fewer corners than 10 and the same tracks:
    docs/notebook/real-data.md, "Moved from code comments");
    max_features: cap after grid bucketing into ``grid`` = (cols, rows) cells; window: SAD
    window side (odd); search_radius: max image motion between frames as a fraction of the
    image width; max_sad: mean absolute difference per pixel above which a match is refused;
    stereo_levels: LK pyramid levels for the disparity search.
    """

    fast_threshold: int = 20
    max_features: int = 1000
    grid: tuple[int, int] = (12, 4)
    window: int = 11
    search_radius: float = 0.15
    max_sad: float = 20.0
    stereo_levels: int = 4
    max_stereo_dy: float = 1.0
    max_fb_error: float = 0.5
    min_disparity_px: float = 1.0


class Features(NamedTuple):
    """Corners of one rectified stereo frame with valid disparity."""

    uv: np.ndarray  # [N, 2] float32 pixel positions in the left image
    disparity: np.ndarray  # [N] float64 pixels
    desc: np.ndarray  # [N, window^2] float32 SAD descriptors


def prefilter(img: np.ndarray) -> np.ndarray:
    """Remove the local mean (9x9 box) so SAD is insensitive to exposure changes."""
    f = img.astype(np.float32)
    return f - cv2.blur(f, (9, 9))


def detect(img: np.ndarray, params: FeatureParams = FeatureParams()) -> np.ndarray:
    """FAST corners, strongest first within each grid cell, at most ``max_features`` [N, 2]."""
    h, w = img.shape[:2]
    margin = params.window // 2 + 1
    kps = cv2.FastFeatureDetector_create(params.fast_threshold, True).detect(img)
    if not kps:
        return np.zeros((0, 2), np.float32)
    pts = cv2.KeyPoint_convert(kps).reshape(-1, 2).astype(np.float32)
    score = np.fromiter((k.response for k in kps), np.float32, len(kps))
    inside = ((pts[:, 0] >= margin) & (pts[:, 0] < w - margin)
              & (pts[:, 1] >= margin) & (pts[:, 1] < h - margin))
    pts, score = pts[inside], score[inside]
    gx, gy = params.grid
    cell = (np.minimum(pts[:, 0] * gx // w, gx - 1) * gy
            + np.minimum(pts[:, 1] * gy // h, gy - 1)).astype(np.int64)
    order = np.lexsort((-score, cell))  # by cell, strongest first
    cell_sorted = cell[order]
    first = np.searchsorted(cell_sorted, cell_sorted, side="left")
    rank = np.arange(len(order)) - first
    per_cell = max(1, params.max_features // (gx * gy))
    keep = order[rank < per_cell]
    return pts[keep[np.argsort(-score[keep], kind="stable")]][:params.max_features]


def feature_disparity(left: np.ndarray, right: np.ndarray, uv: np.ndarray,
                      params: FeatureParams = FeatureParams()) -> tuple[np.ndarray, np.ndarray]:
    """Sparse stereo: disparity of each left corner and a validity mask.

    Pyramidal LK from left to right and back; a match must stay on its row (rectified pair),
    return to its start, and have positive disparity.
    """
    if len(uv) == 0:
        return np.zeros(0), np.zeros(0, bool)
    lk = dict(winSize=(params.window, params.window), maxLevel=params.stereo_levels,
              criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    p0 = uv.reshape(-1, 1, 2).astype(np.float32)
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(left, right, p0, None, **lk)
    p0b, st2, _ = cv2.calcOpticalFlowPyrLK(right, left, p1, None, **lk)
    p0, p1, p0b = p0[:, 0], p1[:, 0], p0b[:, 0]
    disp = (p0[:, 0] - p1[:, 0]).astype(np.float64)
    ok = ((st1[:, 0] == 1) & (st2[:, 0] == 1)
          & (np.abs(p1[:, 1] - p0[:, 1]) < params.max_stereo_dy)
          & (np.linalg.norm(p0b - p0, axis=1) < params.max_fb_error)
          & (disp >= params.min_disparity_px))
    return disp, ok


def dense_feature_disparity(disparity: np.ndarray, uv: np.ndarray,
                            params: FeatureParams = FeatureParams(), max_spread: float = 1.0
                            ) -> tuple[np.ndarray, np.ndarray]:
    """Feature disparity read from the dense disparity map (paper sec. 4: the stereo correlator
    has already measured it): bilinear at the sub-pixel corner; valid where all four neighbours
    are valid and agree within ``max_spread`` px (not across a depth edge)."""
    if len(uv) == 0:
        return np.zeros(0), np.zeros(0, bool)
    h, w = disparity.shape
    x = np.clip(uv[:, 0].astype(np.float64), 0, w - 1.001)
    y = np.clip(uv[:, 1].astype(np.float64), 0, h - 1.001)
    x0, y0 = x.astype(np.int64), y.astype(np.int64)
    fx, fy = x - x0, y - y0
    q = np.stack([disparity[y0, x0], disparity[y0, x0 + 1], disparity[y0 + 1, x0],
                  disparity[y0 + 1, x0 + 1]]).astype(np.float64)
    with np.errstate(invalid="ignore"):
        disp = ((1 - fy) * ((1 - fx) * q[0] + fx * q[1]) + fy * ((1 - fx) * q[2] + fx * q[3]))
        ok = (np.isfinite(q).all(0) & (q.max(0) - q.min(0) <= max_spread)
              & (disp >= params.min_disparity_px))
    return np.where(ok, disp, 0.0), ok


def describe(filtered: np.ndarray, uv: np.ndarray, window: int) -> np.ndarray:
    """[N, window^2] float32 pixel windows of the prefiltered image centred on each corner."""
    r = window // 2
    if len(uv) == 0:
        return np.zeros((0, window * window), np.float32)
    iu = np.rint(uv[:, 0]).astype(np.int64)
    iv = np.rint(uv[:, 1]).astype(np.int64)
    off = np.arange(-r, r + 1)
    rows = iv[:, None, None] + off[None, :, None]
    cols = iu[:, None, None] + off[None, None, :]
    return np.ascontiguousarray(filtered[rows, cols].reshape(len(uv), -1), dtype=np.float32)


def match_sad(a: Features, b: Features, radius_px: float, max_sad: float) -> np.ndarray:
    """Mutually best SAD matches within ``radius_px``; returns [K, 2] index pairs (i in a, j in b).

    Nearest neighbours under the L1 norm in both directions with ``cv2.batchDistance`` (masked to
    candidates within the radius), so no per-match Python objects are made.
    """
    if len(a.uv) == 0 or len(b.uv) == 0:
        return np.zeros((0, 2), np.int64)
    dx = a.uv[:, None, 0] - b.uv[None, :, 0]
    dy = a.uv[:, None, 1] - b.uv[None, :, 1]
    near = (dx * dx + dy * dy <= radius_px * radius_px).astype(np.uint8)
    dist, fwd = cv2.batchDistance(a.desc, b.desc, cv2.CV_32F, normType=cv2.NORM_L1, K=1,
                                  mask=near)
    _, bwd = cv2.batchDistance(b.desc, a.desc, cv2.CV_32F, normType=cv2.NORM_L1, K=1,
                               mask=np.ascontiguousarray(near.T))
    dist, fwd, bwd = dist[:, 0], fwd[:, 0], bwd[:, 0]
    ok = (fwd >= 0) & (dist <= max_sad * a.desc.shape[1])
    i = np.nonzero(ok)[0]
    i = i[bwd[fwd[i]] == i]
    return np.column_stack([i, fwd[i]]).astype(np.int64).reshape(-1, 2)


def refine_matches(img_a: np.ndarray, img_b: np.ndarray, uv_a: np.ndarray, uv_b: np.ndarray,
                   window: int, max_shift: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel positions in b for corners at ``uv_a`` seeded at their SAD matches ``uv_b``.

    Returns the refined positions and a mask of those that converged within ``max_shift`` px.
    """
    if len(uv_a) == 0:
        return uv_b, np.zeros(0, bool)
    p1, st, _ = cv2.calcOpticalFlowPyrLK(
        img_a, img_b, uv_a.reshape(-1, 1, 2).astype(np.float32),
        uv_b.reshape(-1, 1, 2).astype(np.float32).copy(), winSize=(window, window), maxLevel=0,
        criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01),
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    p1 = p1[:, 0]
    ok = (st[:, 0] == 1) & (np.linalg.norm(p1 - uv_b, axis=1) < max_shift)
    return np.where(ok[:, None], p1, uv_b), ok
