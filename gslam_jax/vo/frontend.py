"""The stereo front-end loop shared by the dataset adapters: images -> Run.

Per frame (DESIGN "Data flow"): load and rectify the pair, stereo VO increment (or the documented
fallback), 6-DoF pose integration with gravity tilt correction, dense disparity -> points in the
gravity-aligned robot frame, streamed into local maps. Bad frames either raise (``on_bad_frame=
"error"``) or are handled by the fallback and counted (``"fallback"``).
"""

from __future__ import annotations

import warnings
from collections import Counter, defaultdict
from dataclasses import dataclass, field, replace
from typing import Callable, NamedTuple

import numpy as np

from gslam_jax.vo.localmap import LocalMapBuilder, LocalMapParams, map_axes_heading
from gslam_jax.run import Run, validate_run
from gslam_jax.vo.calib import ImageError, RectifiedRig
from gslam_jax.vo.disparity_noise import DisparityNoise, depth_errors, temporal_residuals
from gslam_jax.vo.estimate import Camera
from gslam_jax.vo.fallback import (correct_tilt, fallback_increment, level_rotation,
                                   planar_transform, slip_ratio)
from gslam_jax.vo.geometry import increments_2d, invert, pose_to_2d
from gslam_jax.vo.odometry import StereoVO, VOParams, VOResult
from gslam_jax.vo.stereo import (NEAREST_DENSE_DEPTH, DenseStereoParams, dense_disparity,
                                 disparity_to_points, drop_depth_edges, to_robot_frame,
                                 with_calibrated_range)

__all__ = ["FrontEndParams", "FrontEndSummary", "FrontEndResult", "SensorAids", "run_frontend"]

PairLoader = Callable[[int], tuple[np.ndarray, np.ndarray]]
ExtraPairs = Callable[[int], list[tuple[np.ndarray, np.ndarray, np.ndarray]]]
"""``extra(t)`` -> [(left, right, t_robot_cam)]: more rectified pairs (same rig) seen at frame t,
used for dense points only (e.g. the second pair of a two-pair robot)."""


@dataclass(frozen=True)
class FrontEndParams:
    """Front-end settings. ``dense=False`` skips dense stereo (VO only; local maps stay empty).

    on_bad_frame: "error" raises on a missing/corrupt/mis-sized image; "fallback" treats the frame
    as a VO failure (fallback increment, no points) and counts it in the summary.
    tilt_gain, tilt_gate: gravity tilt correction (see ``fallback.correct_tilt``).
    """

    vo: VOParams = field(default_factory=VOParams)
    stereo: DenseStereoParams = field(default_factory=DenseStereoParams)
    local_map: LocalMapParams = field(default_factory=LocalMapParams)
    dense: bool = True
    on_bad_frame: str = "error"
    tilt_gain: float = 0.05
    tilt_gate: float = 0.3


class SensorAids(NamedTuple):
    """Optional per-frame wheel/IMU data, all in the robot frame; None where absent.

    wheel: [T, 3] wheel-odometry increments; imu_yaw: [T] gyro yaw increments (rad);
    accel: [T, 3] accelerometer specific force at each frame (m/s^2).
    """

    wheel: np.ndarray | None = None
    imu_yaw: np.ndarray | None = None
    accel: np.ndarray | None = None


@dataclass
class FrontEndSummary:
    """Counts for the run summary: VO failures by reason, bad frames, control sources."""

    frames: int = 0
    failures: dict[str, list[int]] = field(default_factory=lambda: defaultdict(list))
    bad_frames: list[tuple[int, str]] = field(default_factory=list)
    sources: Counter = field(default_factory=Counter)
    tilt_corrections: int = 0
    dropped_points: int = 0
    far_points: int = 0  # points over [stereo] max_depth_error, not made
    disparity_noise: DisparityNoise | None = None

    @property
    def vo_failures(self) -> int:
        return sum(len(v) for v in self.failures.values())

    def text(self) -> str:
        lines = [f"frames: {self.frames}, VO failures: {self.vo_failures}, "
                 f"bad frames: {len(self.bad_frames)}, control sources: {dict(self.sources)}"]
        lines += [f"  VO failure '{k}': frames {v}" for k, v in sorted(self.failures.items())]
        lines += [f"  bad frame {t}: {msg}" for t, msg in self.bad_frames]
        if self.disparity_noise is not None and self.disparity_noise.text():
            lines.append(f"disparity noise measured (sigma by disparity, the last ~10 frames): "
                         f"{self.disparity_noise.text()}")
        if self.far_points:
            lines.append(f"points over [stereo] max_depth_error, not made: {self.far_points}")
        return "\n".join(lines)


class FrontEndResult(NamedTuple):
    run: Run
    summary: FrontEndSummary
    poses: np.ndarray  # [T, 4, 4] robot poses (VO + fallback) in the world frame
    vo: list[VOResult]
    slip: np.ndarray | None  # [T] slip ratio where wheels and VO are both available


def run_frontend(load_pair: PairLoader, num_frames: int, rig: RectifiedRig,
                 t_robot_cam: np.ndarray, timestamps: np.ndarray,
                 params: FrontEndParams = FrontEndParams(), *,
                 aids: SensorAids = SensorAids(), ground_truth: np.ndarray | None = None,
                 initial_pose: np.ndarray | None = None, source: str = "<stereo>",
                 extra_pairs: ExtraPairs | None = None,
                 progress: Callable[[int, int], None] | None = None,
                 time_origin_ns: int | None = None) -> FrontEndResult:
    """Process ``num_frames`` raw stereo pairs (``load_pair(t)``) into a validated Run.

    ``t_robot_cam``: 4x4 rectified-left-camera mount in the robot body frame (x fwd, y left,
    z up, origin on the ground). ``initial_pose``: (x, y, theta) of frame 0 in the world frame.
    With ``params.dense`` the dense disparity is computed first and, when
    ``params.vo.disparity == "dense"``, VO reads its feature disparities from it (paper sec. 4).
    ``extra_pairs``: see :data:`ExtraPairs` (needs ``params.dense``). ``progress(done,
    total)`` is called every few frames; ``time_origin_ns`` goes into the Run unchanged.
    """
    if params.on_bad_frame not in ("error", "fallback"):
        raise ValueError(f"on_bad_frame must be 'error' or 'fallback', got {params.on_bad_frame!r}")
    cam = Camera(rig.fx, rig.fy, rig.cx, rig.cy, rig.baseline)
    params = replace(params, stereo=with_calibrated_range(params.stereo, rig))
    nearest = rig.fx * rig.baseline / max(params.stereo.num_disparities, 1)
    if params.dense and nearest > NEAREST_DENSE_DEPTH:
        warnings.warn(f"{source}: dense stereo with {params.stereo.num_disparities} disparities "
                      f"covers depths from {nearest:.1f} m (fx * baseline = "
                      f"{rig.fx * rig.baseline:.0f} px m); nearer surfaces will be matched as "
                      "far points: raise stereo.num_disparities", stacklevel=2)
    vo = StereoVO(cam, params.vo)
    matcher = params.stereo.matcher() if params.dense else None
    max_depth = params.local_map.max_range * 1.5
    noise = DisparityNoise(prior_std=params.stereo.disparity_std)
    summary = FrontEndSummary(frames=num_frames, disparity_noise=noise)
    max_error = params.stereo.max_depth_error
    prev_disp = None

    def points_of(disparity: np.ndarray) -> np.ndarray:
        """Camera-frame points of a disparity map: none at depth edges, none deeper than
        ``max_depth``, and none whose depth error is over ``[stereo] max_depth_error``."""
        pts = disparity_to_points(drop_depth_edges(disparity, params.stereo.edge_ratio), rig,
                                  params.stereo.stride, max_range=max_depth)
        if not np.isfinite(max_error):
            return pts
        keep = depth_errors(pts, rig, noise) <= max_error
        summary.far_points += int((~keep).sum())
        return pts[keep]

    m, m_inv = t_robot_cam, invert(t_robot_cam)
    start = np.zeros(3) if initial_pose is None else np.asarray(initial_pose, dtype=np.float64)
    builder = LocalMapBuilder(params.local_map,
                              axes_heading=map_axes_heading(params.local_map.axes, start))
    pose = planar_transform(start)
    poses, poses_2d, results, failed, maps, obs_index = [], [], [], [], [], []
    controls = np.zeros((num_frames, 3))
    every = max(num_frames // 100, 1)
    for t in range(num_frames):
        if progress is not None and t and t % every == 0:
            progress(t, num_frames)
        pair = None
        try:
            pair = rig.rectify(*load_pair(t), frame=f"{source} frame {t}")
        except ImageError as err:
            if params.on_bad_frame == "error":
                raise
            summary.bad_frames.append((t, str(err)))
            vo.reset()
        disp = (dense_disparity(*pair, params.stereo, matcher)
                if params.dense and pair is not None else None)
        res = vo.step(*pair, disparity=disp) if pair is not None else VOResult(
            False, np.eye(4), "bad frame", 0, 0, 0, np.nan, np.full((6, 6), np.nan))
        results.append(res)
        if np.isfinite(max_error) and disp is not None and prev_disp is not None and res.ok:
            noise.update(*temporal_residuals(prev_disp, disp, res.transform, rig,
                                             params.stereo.stride,
                                             params.stereo.num_disparities))
        prev_disp = disp
        prev_2d = pose_to_2d(pose)
        if t == 0:
            failed.append(False)
        elif res.ok:
            pose = pose @ m @ res.transform @ m_inv
            failed.append(False)
            summary.sources["vo"] += 1
        else:
            pick = lambda a: None if a is None else a[t]  # noqa: E731
            u, src = fallback_increment(controls[t - 1], pick(aids.wheel), pick(aids.imu_yaw))
            new_2d = prev_2d + np.array([np.cos(prev_2d[2]) * u[0] - np.sin(prev_2d[2]) * u[1],
                                         np.sin(prev_2d[2]) * u[0] + np.cos(prev_2d[2]) * u[1],
                                         u[2]])
            tilt = level_rotation(pose[:3, :3])
            z = pose[2, 3]
            pose = planar_transform(new_2d)
            pose[:3, :3] = pose[:3, :3] @ tilt
            pose[2, 3] = z
            failed.append(True)
            summary.failures[res.reason if res.reason != "first frame" else "no previous frame"
                              ].append(t)
            summary.sources[src] += 1
        if aids.accel is not None:
            pose[:3, :3], applied = correct_tilt(pose[:3, :3], aids.accel[t], params.tilt_gain,
                                                 params.tilt_gate)
            summary.tilt_corrections += int(applied)
        poses.append(pose.copy())
        poses_2d.append(pose_to_2d(pose))
        if t > 0:
            controls[t] = increments_2d(np.stack([prev_2d, poses_2d[-1]]))[1]
        points = np.zeros((0, 3))
        if disp is not None:
            r_level = level_rotation(pose[:3, :3])
            parts = [to_robot_frame(points_of(disp), m, r_level)]
            for left, right, mount in (extra_pairs(t) if extra_pairs is not None else []):
                d2 = dense_disparity(left, right, params.stereo, matcher)
                parts.append(to_robot_frame(points_of(d2), mount, r_level))
            points = np.concatenate(parts)
        stats = builder.add(poses_2d[-1], points)
        if t == 0 and stats is None:
            stats = builder.flush()
        obs_index.append(len(maps) if stats is not None else -1)
        if stats is not None:
            maps.append(stats)
    if progress is not None:
        progress(num_frames, num_frames)
    summary.dropped_points = builder.dropped_points
    L = params.local_map.size
    slip = None
    if aids.wheel is not None:
        dt = np.maximum(np.diff(np.asarray(timestamps, float), prepend=np.nan), 1e-9)
        s_wheel = np.hypot(aids.wheel[:, 0], aids.wheel[:, 1]) / dt
        s_vo = np.where(np.asarray(failed), np.nan, np.hypot(controls[:, 0], controls[:, 1]) / dt)
        slip = slip_ratio(s_wheel, s_vo)
    run = Run(controls=controls, obs_index=np.asarray(obs_index, np.int32),
              local_maps=np.stack(maps) if maps else np.zeros((0, L, L, 3)),
              resolution=params.local_map.resolution,
              timestamps=np.asarray(timestamps, np.float64), ground_truth=ground_truth,
              vo_failed=np.asarray(failed, bool), initial_pose=start,
              time_origin_ns=time_origin_ns, sensor="stereo",
              lattice_headings=(None if params.local_map.lattice == "robot"
                                else np.asarray(builder.lattice_headings, np.float64)))
    return FrontEndResult(validate_run(run, source), summary, np.stack(poses), results, slip)
