"""EuRoC ASL adapter: ``mav0/{cam0,cam1}/{sensor.yaml,data.csv,data/*.png}``, ``mav0/imu0``,
``mav0/state_groundtruth_estimate0/data.csv`` (optional).

The raw images are distorted (radial-tangential) and unrectified; rectification comes from the
two ``sensor.yaml`` files (intrinsics, distortion, T_BS). The robot frame is fixed to the body at
frame 0: z up along the mean accelerometer reading (gravity), x forward along the cam0 optical
axis made horizontal, origin ``height`` metres below the body (ground-truth z at the first frame
with ground truth when there is any, else 0). That makes cam0's default mount; the config's
[rig] changes it (``datasets.mount.camera_mount``, ``EurocParams.mount``), and the robot frame
(ground truth, IMU axes) follows the mount given. The IMU supplies the gravity vector for tilt
correction and gyro yaw increments for the VO fallback; the robot must stand still for
``gravity_window`` seconds from the first frame, where "up" (mean accelerometer) and the gyro bias
(mean gyro, subtracted before integrating yaw) are estimated. The bias is only removed when the
gyro is still there too (see :class:`EurocParams`); otherwise a warning names ``imu0/data.csv``
and the raw gyro is integrated.

Partial logs, as in the original EuRoC downloads: frames before the first or after the last
ground-truth row (by more than 5 ms) get NaN ground-truth rows (a warning says how many; none
covered: no ground truth); the IMU log may start or end up to one frame period (the median frame
interval) after the first / before the last frame; when cam0 and cam1 list different numbers of
frames the first min(n0, n1) pairs are used (a warning names both counts).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from gslam_jax.config import Config
from gslam_jax.datasets.calib_yaml import numbers, open_yaml
from gslam_jax.datasets.mount import camera_mount
from gslam_jax.datasets.reading import (first_not_increasing, quat_to_matrix, read_image,
                                        read_table)
from gslam_jax.datasets.registry import DataSource, LoadedSource, Source, stereo_settings
from gslam_jax.errors import DatasetError
from gslam_jax.run import Run
from gslam_jax.vo.calib import CalibrationError, RectifiedRig
from gslam_jax.vo.fallback import GRAVITY
from gslam_jax.vo.frontend import FrontEndParams, FrontEndResult, SensorAids, run_frontend
from gslam_jax.vo.geometry import invert, make_transform, pose_to_2d
from gslam_jax.vo.localmap import localmap_params
from gslam_jax.vo.stereo import DenseStereoParams

__all__ = ["EurocParams", "CameraYaml", "read_sensor_yaml", "euroc_rig", "find_mav0",
           "euroc_frontend", "load_euroc"]


@dataclass(frozen=True)
class EurocParams:
    """max_frames: process at most this many frames; height: metres from body to ground
    (None: ground-truth z at the first frame with ground truth, else 0); gravity_window: seconds
    of IMU after the first frame, with the robot at rest, whose samples with ||a| - g| <
    ``frontend.tilt_gate`` are averaged to find "up" (accelerometer) and the gyro bias.

    The gyro mean over those samples is only subtracted as the bias when the gyro is still there:
    the norm of its per-axis standard deviation below ``gyro_still`` (rad/s) and the norm of the
    mean itself below ``max_gyro_bias`` (rad/s; the EuRoC ADIS16448 bias is about 0.08). A steady
    rotation at the start passes the accelerometer test but not these; then no bias is removed
    and a warning names ``imu0/data.csv``.

    mount: None, or a function of the default mount of raw cam0 (4x4, camera to robot, as
    computed above) returning the one to use instead (``gslam run``: the config's [rig]
    through ``datasets.mount.camera_mount``)."""

    max_frames: int | None = None
    height: float | None = None
    gravity_window: float = 0.1
    gyro_still: float = 0.02
    max_gyro_bias: float = 0.12
    frontend: FrontEndParams = field(default_factory=FrontEndParams)
    mount: Callable[[np.ndarray], np.ndarray] | None = None


@dataclass(frozen=True)
class CameraYaml:
    k: np.ndarray
    dist: np.ndarray
    t_bs: np.ndarray
    size: tuple[int, int]
    source: str = "<sensor.yaml>"  # the file it was read from, for error messages


def read_sensor_yaml(path: Path) -> CameraYaml:
    """Intrinsics (fu, fv, cu, cv), radial-tangential distortion, T_BS and resolution.

    CalibrationError naming the file and field for a missing or non-numeric entry, fu/fv or a
    resolution that is not positive, or a T_BS that is not a rigid transform.
    """
    fs = open_yaml(path)
    model = fs.getNode("distortion_model").string()
    if model and model != "radial-tangential":
        raise CalibrationError(f"{path}: field 'distortion_model': {model!r} is not supported")
    fu, fv, cu, cv = numbers(fs.getNode("intrinsics"), "intrinsics", 4, path)
    dist = numbers(fs.getNode("distortion_coefficients"), "distortion_coefficients", 4, path)
    t_bs = numbers(fs.getNode("T_BS"), "T_BS", 16, path).reshape(4, 4)
    w, h = numbers(fs.getNode("resolution"), "resolution", 2, path)
    fs.release()
    if not (fu > 0 and fv > 0):
        raise CalibrationError(f"{path}: field 'intrinsics': fu and fv must be positive, "
                               f"got {fu}, {fv}")
    if not (w > 0 and h > 0 and w == int(w) and h == int(h)):
        raise CalibrationError(f"{path}: field 'resolution': width and height must be positive "
                               f"integers, got {w}, {h}")
    if not np.allclose(t_bs[3], [0.0, 0.0, 0.0, 1.0], rtol=0.0, atol=1e-9):
        raise CalibrationError(f"{path}: field 'T_BS': bottom row must be [0, 0, 0, 1], "
                               f"got {t_bs[3].tolist()}")
    if not np.allclose(t_bs[:3, :3] @ t_bs[:3, :3].T, np.eye(3), atol=1e-3):
        raise CalibrationError(f"{path}: field 'T_BS': the rotation part is not orthonormal")
    k = np.array([[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]])
    return CameraYaml(k, dist, t_bs, (int(w), int(h)), str(path))


def euroc_rig(cam0: CameraYaml, cam1: CameraYaml) -> RectifiedRig:
    """Rectified rig from the two cameras' calibration (pose of cam0 in cam1 from the T_BS)."""
    source = f"{cam0.source} + {cam1.source}"
    if cam0.size != cam1.size:
        raise CalibrationError(f"{source}: cam0 is {cam0.size} but cam1 is {cam1.size}")
    t_10 = invert(cam1.t_bs) @ cam0.t_bs
    return RectifiedRig.from_raw(cam0.k, cam0.dist, cam1.k, cam1.dist, t_10[:3, :3], t_10[:3, 3],
                                 cam0.size, source)


def _frames(cam_dir: Path) -> tuple[np.ndarray, list[Path]]:
    """Timestamps (ns, increasing) and image paths of ``data.csv`` (``timestamp,filename``)."""
    csv = cam_dir / "data.csv"
    if not csv.is_file():
        raise FileNotFoundError(f"{csv}: missing frame list")
    stamps: list[int] = []
    paths: list[Path] = []
    for n, line in enumerate(csv.read_text(errors="replace").splitlines(), 1):
        if not line.strip() or line.startswith("#"):
            continue
        fields = [f.strip() for f in line.split(",")]
        if len(fields) < 2 or not fields[1]:
            raise DatasetError(f"{csv}:{n}: expected 'timestamp,filename', got {line.strip()!r}")
        try:
            stamp = int(fields[0])
        except ValueError:
            raise DatasetError(f"{csv}:{n}: timestamp {fields[0]!r} is not an integer "
                               "(nanoseconds)") from None
        if stamps and stamp <= stamps[-1]:
            raise DatasetError(f"{csv}:{n}: timestamp {stamp} is not after {stamps[-1]} "
                               "(frames must be in time order)")
        stamps.append(stamp)
        paths.append(cam_dir / "data" / fields[1])
    if not stamps:
        raise DatasetError(f"{csv}: no frames listed")
    return np.array(stamps, np.int64), paths


def _robot_from_body(up_b: np.ndarray, fwd_b: np.ndarray, height: float) -> np.ndarray:
    """T_body_robot: robot axes (x forward, y left, z up) in the body frame, origin on the
    ground."""
    up = up_b / np.linalg.norm(up_b)
    fwd = fwd_b - up * (fwd_b @ up)
    fwd /= np.linalg.norm(fwd)
    return make_transform(np.column_stack([fwd, np.cross(up, fwd), up]), -height * up)


def _read_imu(path: Path, ts: np.ndarray,
              period: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IMU times (ns), gyro (rad/s) and accelerometer (m/s^2) of ``imu0/data.csv``.

    The log may start up to ``period`` ns (one frame period) after the first frame ``ts`` and end
    up to ``period`` ns before the last one; inside its span every frame interval needs samples.
    """
    table = read_table(path, 7, ",", int_first=True)
    imu_t, gyro, acc = table.stamps, table.data[:, 1:4], table.data[:, 4:7]
    i = first_not_increasing(imu_t)
    if i is not None:
        raise DatasetError(f"{path}:{table.lines[i]}: timestamp {imu_t[i]} is "
                           f"not after {imu_t[i - 1]} (samples must be in time order)")
    if imu_t[0] > ts[0] + period:
        raise DatasetError(f"{path}: IMU log starts at {imu_t[0]} ns, after frame 0 ({ts[0]} ns) "
                           f"by {(imu_t[0] - ts[0]) * 1e-6:.1f} ms, more than one frame period "
                           f"({period * 1e-6:.1f} ms)")
    if imu_t[-1] < ts[-1] - period:
        t = int(np.argmax(ts > imu_t[-1] + period))
        raise DatasetError(f"{path}: IMU log ends at {imu_t[-1]} ns, before frame {t} ({ts[t]} ns) "
                           f"by {(ts[t] - imu_t[-1]) * 1e-6:.1f} ms, more than one frame period "
                           f"({period * 1e-6:.1f} ms)")
    edges = np.searchsorted(imu_t, ts, side="right")
    # Empty frame intervals inside the log's span are gaps; those before its start or after its
    # end (within the tolerance above) are not.
    empty = np.flatnonzero((np.diff(edges) == 0) & (ts[1:] >= imu_t[0]) & (ts[:-1] < imu_t[-1]))
    if empty.size:
        t = int(empty[0]) + 1
        raise DatasetError(f"{path}: no IMU samples between frame {t - 1} ({ts[t - 1]} ns) and "
                           f"frame {t} ({ts[t]} ns)")
    return imu_t, gyro, acc


GT_TOLERANCE_NS = 5_000_000  # a frame takes the ground-truth row nearest in time, within 5 ms


def _ground_truth(path: Path, ts: np.ndarray) -> np.ndarray:
    """Body-to-world 4x4 pose [T, 4, 4] of each frame ``ts`` from the ground-truth csv (time, p,
    q_wxyz ...): the row nearest in time, which must be within 5 ms. Frames outside the log's
    span (before its first row or after its last by 5 ms or more) get NaN poses; a frame inside
    the span without a row within 5 ms (a gap in the log) is an error naming the file and frame."""
    table = read_table(path, 8, ",", at_least=True, int_first=True)
    g, g_t = table.data, table.stamps
    i = first_not_increasing(g_t)
    if i is not None:
        raise DatasetError(f"{path}:{table.lines[i]}: timestamp {g_t[i]} is "
                           f"not after {g_t[i - 1]} (rows must be in time order)")
    idx = np.clip(np.searchsorted(g_t, ts), 0, len(g) - 1)
    prev = np.maximum(idx - 1, 0)
    idx = np.where(np.abs(g_t[prev] - ts) < np.abs(g_t[idx] - ts), prev, idx)
    off = np.abs(g_t[idx] - ts)
    inside = (ts > g_t[0] - GT_TOLERANCE_NS) & (ts < g_t[-1] + GT_TOLERANCE_NS)
    gap = inside & (off >= GT_TOLERANCE_NS)
    if gap.any():
        t = int(np.argmax(gap))
        raise DatasetError(f"{path}: no ground-truth row within 5 ms of frame {t} ({ts[t]} ns); "
                           f"the nearest is {off[t] * 1e-6:.1f} ms away (a gap in the log, which "
                           f"spans {g_t[0]} to {g_t[-1]} ns)")
    poses = np.full((len(ts), 4, 4), np.nan)
    for t in np.flatnonzero(inside):
        r = g[idx[t]]
        poses[t] = make_transform(quat_to_matrix(r[4:8]), r[1:4])
    return poses


def find_mav0(root: str | Path) -> Path:
    """The ``mav0`` folder of an EuRoC ASL folder ``root`` (``root`` itself where it holds
    ``cam0``). FileNotFoundError otherwise: one suggesting the dataset's root where ``root``
    lies inside it (e.g. at ``mav0/cam0``), or a KITTI layout's source."""
    root = Path(root)
    if (root / "mav0").is_dir():
        return root / "mav0"
    if (root / "cam0").is_dir():
        return root
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such folder")
    for up in root.absolute().parents[:4]:
        if up.name == "mav0" or (up / "mav0").is_dir():
            top = up.parent if up.name == "mav0" else up
            raise FileNotFoundError(f"{root}: lies inside the EuRoC folder {top}: give --path "
                                    f"{top} (the folder holding mav0/)")
    hint = ("; it looks like a KITTI odometry folder (sequences/): --source kitti"
            if (root / "sequences").is_dir() else "")
    raise FileNotFoundError(f"{root}: no 'mav0' folder (expected the EuRoC ASL layout, "
                            f"DIR/mav0/cam0/...){hint}")


def euroc_frontend(root: str | Path, params: EurocParams = EurocParams(), *,
                   progress: Callable[[int, int], None] | None = None) -> FrontEndResult:
    """Run the stereo front-end over an EuRoC ASL folder (``root`` holds ``mav0``).

    The Run's timestamps are seconds from the first frame; ``Run.time_origin_ns`` keeps that
    frame's stamp (EuRoC's nanosecond clock) for the TUM outputs. ``progress(done, total)``
    follows the frames.

    Warns (``warnings.warn``) when trailing frames of one camera are dropped, when ground truth
    covers only some frames (NaN rows for the others) or none (the run has no ground truth), and
    when the gyro is not still in the gravity window (no bias removed); see the module docstring.
    """
    mav = find_mav0(root)
    cam0, cam1 = (read_sensor_yaml(mav / c / "sensor.yaml") for c in ("cam0", "cam1"))
    rig = euroc_rig(cam0, cam1)
    if params.max_frames is not None and params.max_frames < 1:
        raise DatasetError(f"max_frames must be at least 1, got {params.max_frames}")
    ts0, left = _frames(mav / "cam0")
    ts1, right = _frames(mav / "cam1")
    n0, n1 = len(ts0), len(ts1)
    wanted = max(n0, n1) if params.max_frames is None else min(max(n0, n1), params.max_frames)
    n = min(n0, n1, wanted)
    if n < wanted:
        longer = "cam0" if n0 > n1 else "cam1"
        warnings.warn(f"{mav}: cam0/data.csv lists {n0} frames but cam1/data.csv {n1}; using the "
                      f"first {n} stereo pairs ({wanted - n} trailing frame(s) of {longer} "
                      "dropped)", stacklevel=2)
    if not np.array_equal(ts0[:n], ts1[:n]):
        bad = int(np.argmax(ts0[:n] != ts1[:n]))
        raise DatasetError(f"{mav}: cam0 and cam1 timestamps differ at frame {bad} "
                           f"({ts0[bad]} vs {ts1[bad]} ns in data.csv)")
    ts = ts0[:n]
    imu_csv = mav / "imu0" / "data.csv"
    if not imu_csv.is_file():
        raise FileNotFoundError(f"{imu_csv}: missing (needed for the gravity direction)")
    period = int(np.median(np.diff(ts0))) if len(ts0) > 1 else 0  # the frame period, ns
    imu_t, gyro, acc = _read_imu(imu_csv, ts, period)
    first = (imu_t >= ts[0]) & (imu_t <= ts[0] + int(params.gravity_window * 1e9))
    if not first.any():
        raise DatasetError(f"{imu_csv}: no IMU samples within {params.gravity_window} s of frame 0")
    # At rest: |a| close to g. Those samples give "up" and the gyro bias.
    still = first & (np.abs(np.linalg.norm(acc, axis=1) - GRAVITY) < params.frontend.tilt_gate)
    if not still.any():
        raise DatasetError(f"{imu_csv}: no IMU sample within {params.gravity_window} s of frame 0 "
                           f"has |a| within {params.frontend.tilt_gate} m/s^2 of g; the robot must "
                           "stand still there (gravity and gyro bias)")
    up_b = acc[still].mean(axis=0)
    # The gyro must be still too (a steady rotation passes the |a| test): then its mean is the
    # bias, removed before integrating yaw.
    bias = gyro[still].mean(axis=0)
    spread = float(np.linalg.norm(gyro[still].std(axis=0)))
    if spread < params.gyro_still and np.linalg.norm(bias) < params.max_gyro_bias:
        gyro = gyro - bias
    else:
        warnings.warn(f"{imu_csv}: the gyro is not still within {params.gravity_window} s of "
                      f"frame 0 (mean {np.linalg.norm(bias):.3f} rad/s, limit "
                      f"{params.max_gyro_bias}; spread {spread:.3f} rad/s, limit "
                      f"{params.gyro_still}): no gyro bias removed", stacklevel=2)

    gt_csv = mav / "state_groundtruth_estimate0" / "data.csv"
    gt_body, first_gt = None, 0
    if gt_csv.is_file():
        gt_body = _ground_truth(gt_csv, ts)
        covered = np.flatnonzero(np.isfinite(gt_body[:, 0, 0]))
        if not covered.size:
            warnings.warn(f"{gt_csv}: the ground truth covers none of the {n} frames "
                          f"({ts[0]} to {ts[-1]} ns); the run has no ground truth", stacklevel=2)
            gt_body = None
        else:
            first_gt = int(covered[0])
            if covered.size < n:
                warnings.warn(f"{gt_csv}: the ground truth covers frames {first_gt} to "
                              f"{int(covered[-1])} of {n} only; the others get NaN ground-truth "
                              f"rows (height and initial pose from frame {first_gt})",
                              stacklevel=2)
    height = params.height if params.height is not None else (
        gt_body[first_gt][2, 3] if gt_body is not None else 0.0)
    t_body_robot = _robot_from_body(up_b, cam0.t_bs[:3, 2], height)
    default = invert(t_body_robot) @ cam0.t_bs  # raw cam0 to robot
    mount = default if params.mount is None else params.mount(default)
    if not np.array_equal(mount, default):
        t_body_robot = cam0.t_bs @ invert(mount)
    t_raw_rect = make_transform(rig.r_left.T, np.zeros(3))
    t_robot_cam = mount @ t_raw_rect
    gt = None if gt_body is None else np.stack([
        pose_to_2d(b @ t_body_robot) if np.isfinite(b).all() else np.full(3, np.nan)
        for b in gt_body])

    # Per frame: mean specific force and yaw increment (gyro about "up") since the last frame.
    r_rb = t_body_robot[:3, :3].T
    accel, yaw = np.zeros((n, 3)), np.zeros(n)
    edges = np.searchsorted(imu_t, ts, side="right")
    for t in range(n):
        lo = edges[t - 1] if t else max(edges[0] - 1, 0)
        near = min(lo, len(imu_t) - 1)  # after the log's end: its last sample
        sel = slice(near, max(edges[t], near + 1))
        accel[t] = r_rb @ acc[sel].mean(axis=0)
        if t:
            # Each sample's rate over the time since the previous sample; what the log covers.
            start = max(lo - 1, 0)
            dt = np.diff(imu_t[start:edges[t]]) * 1e-9
            w_up = gyro[start + 1:edges[t]] @ t_body_robot[:3, 2]
            yaw[t] = float(np.sum(w_up * dt))

    def load(t: int) -> tuple[np.ndarray, np.ndarray]:
        return read_image(left[t]), read_image(right[t])

    return run_frontend(load, n, rig, t_robot_cam, (ts - ts[0]) * 1e-9, params.frontend,
                        aids=SensorAids(imu_yaw=yaw, accel=accel), ground_truth=gt,
                        initial_pose=None if gt is None else gt[first_gt], source=str(mav),
                        progress=progress, time_origin_ns=int(ts[0]))


def load_euroc(root: str | Path, params: EurocParams = EurocParams()) -> Run:
    """The Run of an EuRoC ASL sequence (see :func:`euroc_frontend` for the summary)."""
    return euroc_frontend(root, params).run


def _load(src: Source, config: Config, progress: Callable[[int, int], None] | None = None
          ) -> LoadedSource:
    default = FrontEndParams(stereo=DenseStereoParams(num_disparities=0))  # from the calibration
    result = euroc_frontend(src.path, EurocParams(
        max_frames=src.max_frames,
        mount=lambda default: camera_mount(config, default, f"--source euroc {src.path}"),
        frontend=FrontEndParams(local_map=localmap_params(config, "stereo"),
                                on_bad_frame=src.on_bad_frame,
                                stereo=stereo_settings(config, default.stereo))),
        progress=progress)
    print(result.summary.text())
    return LoadedSource(result.run, f"EuRoC {src.path}")


SOURCE = DataSource(name="euroc", help="EuRoC ASL layout (DIR/mav0/...)", load=_load,
                    images=True, path="the EuRoC folder, holding mav0/")
