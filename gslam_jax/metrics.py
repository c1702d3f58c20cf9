"""Evaluation (paper 7.1): trajectory error after a 2-D rigid fit, drift, ESS summaries, and the
map built from a fixed pose sequence (the VO-only map the paper shows beside Gamma-SLAM's).

All NumPy, float64.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np

from gslam_jax.gridmap.grid import GridMap, turn_poses  # the one map value; metrics builds them
from gslam_jax.rbpf import cells
from gslam_jax.run import Run, known_positions

__all__ = ["RigidFit", "rigid_fit_2d", "apply_rigid", "rms_after_fit", "final_position_error",
           "drift_per_distance", "path_length", "trajectory_metrics", "errors_over_known_frames",
           "drift_over_known_frames", "ground_truth_in_map_frame", "ess_summary", "GridMap",
           "pose_map", "pose_lattice", "place_local_map", "vo_only_map", "local_cell_centres"]


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


def pose_map(run: Run, poses: np.ndarray, margin: float = 2.0,
             lattice: GridMap | None = None) -> GridMap:
    """Fuse every local map of ``run`` at ``poses`` [T, 3] (one pose per frame) by the conjugate
    update (eq. 14: (k, S) add up), each local cell dropped into the nearest global cell.

    The map lies on ``lattice`` (its origin, shape, resolution and heading; its k and S are not
    used),
    by default one that covers every pose plus the local-map half-width and ``margin`` metres.
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.shape != (run.num_frames, 3):
        raise ValueError(f"poses must have shape [{run.num_frames}, 3], got {poses.shape}")
    if lattice is None:
        lattice = pose_lattice(run, poses, margin)
    k_map = np.zeros(lattice.k.size)
    s_map = np.zeros_like(k_map)
    for t in np.flatnonzero(run.obs_index >= 0):
        flat, k, S = place_local_map(run, t, poses[t], lattice)
        # unbuffered adds: work in the local map's cells, not in the lattice's (a bincount
        # with minlength would allocate the whole lattice at every frame)
        np.add.at(k_map, flat, k)
        np.add.at(s_map, flat, S)
    return lattice._replace(k=k_map.reshape(lattice.shape), S=s_map.reshape(lattice.shape))


def pose_lattice(run: Run, poses: np.ndarray, margin: float = 2.0) -> GridMap:
    """An empty map (k = S = 0) on the lattice that holds every local map of ``run`` placed at
    ``poses`` [T, 3]: every pose plus the local-map half-width and ``margin`` metres."""
    res = float(run.resolution)
    half = 0.5 * run.local_maps.shape[1] * res * math.sqrt(2.0) + margin
    lo = np.floor((poses[:, :2].min(0) - half) / res) * res
    hi = poses[:, :2].max(0) + half
    shape = tuple(int(v) for v in np.ceil((hi - lo) / res))
    return GridMap(np.zeros(shape), np.zeros(shape), (float(lo[0]), float(lo[1])), res)


@functools.lru_cache(maxsize=8)
def local_cell_centres(L: int, res: float) -> tuple[np.ndarray, np.ndarray]:
    """x, y [L, L] of a local map's cell centres in the robot frame (computed once per shape,
    not once per frame)."""
    centres = (np.arange(L) - L // 2 + 0.5) * res
    cx, cy = np.meshgrid(centres, centres, indexing="ij")
    cx.flags.writeable = cy.flags.writeable = False  # shared between calls
    return cx, cy


def place_local_map(run: Run, t: int, pose: np.ndarray, lattice: GridMap
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame ``t``'s local map placed at ``pose`` [3] on ``lattice`` (``pose_lattice``): the flat
    index of the lattice cell each of its known cells falls in (nearest cell centre), and
    their k and S. The local map's own lattice is turned by its ``Run.lattice_headings``; a
    turned map lattice (``GridMap.heading``) takes the pose on its axes."""
    res = lattice.resolution
    pose = turn_poses(pose, -lattice.heading)
    cx, cy = local_cell_centres(run.local_maps.shape[1], res)
    index = int(run.obs_index[t])
    k, S = np.moveaxis(cells.obs_from_stats(run.local_maps[index]), -1, 0)
    m = k > 0
    x, y, th = pose
    if run.lattice_headings is not None:
        th = th + float(run.lattice_headings[index])
    c, s = math.cos(th), math.sin(th)
    wx = x + c * cx[m] - s * cy[m]
    wy = y + s * cx[m] + c * cy[m]
    i = np.floor((wx - lattice.origin[0]) / res).astype(np.int64)
    j = np.floor((wy - lattice.origin[1]) / res).astype(np.int64)
    return i * lattice.shape[1] + j, np.asarray(k[m]), np.asarray(S[m])


def vo_only_map(run: Run, margin: float = 2.0) -> GridMap:
    """The VO-only map (paper 7.1): local maps fused at the poses integrated from the controls."""
    return pose_map(run, run.vo_poses(), margin)
