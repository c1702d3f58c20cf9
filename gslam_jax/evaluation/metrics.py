"""Evaluation (paper 7.1): trajectory error after a 2-D rigid fit, drift and ESS summaries.
The maps built at fixed poses (the VO-only map the paper shows beside Gamma-SLAM's) are
``gridmap.pose_maps``'s.

All NumPy, float64.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from gslam_jax.run import known_positions

__all__ = ["RigidFit", "rigid_fit_2d", "apply_rigid", "rms_after_fit", "final_position_error",
           "drift_per_distance", "path_length", "trajectory_metrics", "errors_over_known_frames",
           "drift_over_known_frames", "ground_truth_in_map_frame", "ess_summary"]


class RigidFit(NamedTuple):
    """est -> reference: p_ref ~ R @ p_est + t."""

    rotation: np.ndarray  # [2, 2]
    translation: np.ndarray  # [2]
    angle: float  # rad
    rms: float  # RMS distance after the fit (m)


def _xy(a: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] < 2:
        raise ValueError(f"{name} must have shape [N, 2] or [N, 3], got {a.shape}")
    return a[:, :2]


def rigid_fit_2d(estimate: np.ndarray, reference: np.ndarray,
                 weights: np.ndarray | None = None) -> RigidFit:
    """Least-squares rotation + translation (no scale) taking ``estimate`` onto ``reference``.

    Kabsch/Umeyama in 2-D: centre both point sets, the optimal angle is atan2 of the summed
    cross and dot products. Inputs are [N, 2] or [N, 3] poses (only x, y are used).
    """
    p, q = _xy(estimate, "estimate"), _xy(reference, "reference")
    if p.shape != q.shape:
        raise ValueError(f"estimate {p.shape} and reference {q.shape} differ in shape")
    if p.shape[0] == 0:
        raise ValueError("estimate and reference are empty")
    w = np.ones(p.shape[0]) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (p.shape[0],) or (w < 0).any() or w.sum() <= 0:
        raise ValueError("weights must be [N], non-negative, with a positive sum")
    w = w / w.sum()
    mp, mq = w @ p, w @ q
    pc, qc = p - mp, q - mq
    dot = np.sum(w * (pc[:, 0] * qc[:, 0] + pc[:, 1] * qc[:, 1]))
    cross = np.sum(w * (pc[:, 0] * qc[:, 1] - pc[:, 1] * qc[:, 0]))
    angle = math.atan2(cross, dot)
    c, s = math.cos(angle), math.sin(angle)
    R = np.array([[c, -s], [s, c]])
    t = mq - R @ mp
    resid = p @ R.T + t - q
    rms = float(np.sqrt(np.sum(w * np.sum(resid * resid, axis=1))))
    return RigidFit(R, t, angle, rms)


def apply_rigid(poses: np.ndarray, fit: RigidFit) -> np.ndarray:
    """Move poses [N, 2|3] by the fit (headings rotate by the fit angle)."""
    poses = np.asarray(poses, dtype=np.float64)
    out = poses.copy()
    out[:, :2] = poses[:, :2] @ fit.rotation.T + fit.translation
    if poses.shape[1] > 2:
        out[:, 2] = poses[:, 2] + fit.angle
    return out


def rms_after_fit(estimate: np.ndarray, reference: np.ndarray,
                  frames: np.ndarray | None = None) -> float:
    """RMS position error (m) after the best 2-D rigid fit (paper 7.1), over ``frames`` if given
    (e.g. the survey frames), else over all."""
    p, q = _xy(estimate, "estimate"), _xy(reference, "reference")
    if frames is not None:
        p, q = p[frames], q[frames]
    return rigid_fit_2d(p, q).rms


def _align_start(estimate: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Estimate moved so that its first pose coincides with the reference's first pose."""
    est = np.asarray(estimate, dtype=np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    if est.shape[1] < 3 or ref.shape[1] < 3:
        dth = 0.0
    else:
        dth = ref[0, 2] - est[0, 2]
    c, s = math.cos(dth), math.sin(dth)
    R = np.array([[c, -s], [s, c]])
    t = ref[0, :2] - R @ est[0, :2]
    return apply_rigid(est, RigidFit(R, t, dth, float("nan")))


def final_position_error(estimate: np.ndarray, reference: np.ndarray,
                         align: str = "start") -> float:
    """Distance (m) between the last estimated and true positions.

    align="start": the estimate is anchored at the true first pose (dead-reckoning drift);
    align="fit": after the least-squares rigid fit over the whole trajectory.
    """
    if align == "start":
        est = _align_start(estimate, reference)
    elif align == "fit":
        est = apply_rigid(estimate, rigid_fit_2d(estimate, reference))
    else:
        raise ValueError(f"align must be 'start' or 'fit', got {align!r}")
    return float(np.hypot(*(est[-1, :2] - np.asarray(reference, np.float64)[-1, :2])))


def path_length(poses: np.ndarray) -> float:
    """Distance travelled along the positions of ``poses`` (m)."""
    xy = _xy(poses, "poses")
    return float(np.sum(np.hypot(*np.diff(xy, axis=0).T)))


def drift_per_distance(estimate: np.ndarray, reference: np.ndarray) -> float:
    """Start-anchored final position error divided by the true distance travelled."""
    dist = path_length(reference)
    if dist <= 0:
        raise ValueError("reference trajectory does not move; drift per distance is undefined")
    return final_position_error(estimate, reference, align="start") / dist


def drift_over_known_frames(paths: dict[str, np.ndarray], reference: np.ndarray) -> dict:
    """``gt_distance_m``: the ground-truth distance travelled over the frames with a known
    position (NaN rows skipped, a gap bridged by a straight line), and ``{name}_drift_pct``
    per path: its final position error, anchored at the first known frame (which needs a
    finite heading), as a percentage of that distance. Empty with fewer than 2 known frames;
    no drift figures when the ground truth does not move or its first heading is unknown."""
    reference = np.asarray(reference, np.float64)
    frames = np.flatnonzero(known_positions(reference))
    if frames.size < 2:
        return {}
    ref = reference[frames]
    out: dict = {"gt_distance_m": path_length(ref)}
    if out["gt_distance_m"] > 0 and np.isfinite(ref[0, 2]):
        for name, path in paths.items():
            err = final_position_error(np.asarray(path, np.float64)[frames], ref, align="start")
            out[f"{name}_drift_pct"] = 100.0 * err / out["gt_distance_m"]
    return out


def ground_truth_in_map_frame(reference: np.ndarray, path: np.ndarray) -> np.ndarray:
    """The ground truth [T, 3] moved rigidly so that its first known pose (finite position
    and heading) lies on ``path`` at that frame: drawn over a map built from ``path``'s start,
    it shows the drift. NaN rows stay NaN; all NaN when no frame has a known pose."""
    reference = np.asarray(reference, np.float64)
    known = np.flatnonzero(np.all(np.isfinite(reference), axis=1))
    out = np.full_like(reference, np.nan)
    if known.size == 0:
        return out
    f = known[0]
    path = np.asarray(path, np.float64)
    dth = path[f, 2] - reference[f, 2]
    c, sn = math.cos(dth), math.sin(dth)
    R = np.array([[c, -sn], [sn, c]])
    t = path[f, :2] - R @ reference[f, :2]
    rows = np.all(np.isfinite(reference[:, :2]), axis=1)
    out[rows] = apply_rigid(reference[rows], RigidFit(R, t, dth, float("nan")))
    return out


def trajectory_metrics(estimate: np.ndarray, reference: np.ndarray,
                       frames: np.ndarray | None = None) -> dict[str, float]:
    """The figures a run reports: distance, RMS after fit (all frames and ``frames``), final
    errors, drift per distance."""
    out = {
        "distance_m": path_length(reference),
        "rms_m": rms_after_fit(estimate, reference),
        "final_error_m": final_position_error(estimate, reference, "start"),
        "final_error_fit_m": final_position_error(estimate, reference, "fit"),
        "drift_pct": 100.0 * drift_per_distance(estimate, reference),
    }
    if frames is not None and len(frames) >= 2:
        out["rms_survey_m"] = rms_after_fit(estimate, reference, frames)
    return out


def errors_over_known_frames(paths: dict[str, np.ndarray], reference: np.ndarray) -> dict:
    """``{name}_rms_m`` (after the rigid fit) and ``{name}_final_error_m`` (anchored at the first
    scored frame, which needs a finite heading there) of each path, over the frames whose
    reference position is finite (NaN rows: frames without ground truth), and
    ``gt_frames_scored``. No figures with fewer than 2 such frames; with every frame known, the
    figures are exactly ``rms_after_fit`` and ``final_position_error`` over all frames."""
    reference = np.asarray(reference, np.float64)
    frames = np.flatnonzero(known_positions(reference))
    out: dict = {"gt_frames_scored": int(frames.size)}
    if frames.size < 2:
        return out
    every = frames.size == len(reference)
    for name, path in paths.items():
        path = np.asarray(path, np.float64)
        out[f"{name}_rms_m"] = rms_after_fit(path, reference, None if every else frames)
        if np.isfinite(reference[frames[0], 2]):
            out[f"{name}_final_error_m"] = final_position_error(
                path if every else path[frames], reference if every else reference[frames])
    return out


def ess_summary(ess: np.ndarray, num_particles: int,
                resampled: np.ndarray | None = None) -> dict[str, float]:
    """Min / mean / final effective sample size, as fractions of J too, and resample count."""
    ess = np.asarray(ess, dtype=np.float64)
    if num_particles <= 0:
        raise ValueError(f"num_particles must be positive, got {num_particles}")
    out = {"ess_min": float(ess.min()), "ess_mean": float(ess.mean()),
           "ess_final": float(ess[-1]), "ess_min_frac": float(ess.min() / num_particles)}
    if resampled is not None:
        out["resamples"] = int(np.sum(resampled))
    return out
