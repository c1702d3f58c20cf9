"""EuRoC ASL adapter: ``mav0/{cam0,cam1}/{sensor.yaml,data.csv,data/*.png}``, ``mav0/imu0``,
``mav0/state_groundtruth_estimate0/data.csv`` (optional).

The raw images are distorted (radial-tangential) and unrectified; rectification comes from the
two ``sensor.yaml`` files (intrinsics, distortion, T_BS). The robot frame is fixed to the body at
frame 0: z up along the mean accelerometer reading (gravity), x forward along the cam0 optical
axis made horizontal, origin ``height`` metres below the body (ground-truth z at frame 0 when
ground truth is present, else 0). The IMU supplies the gravity vector for tilt correction and
gyro yaw increments for the VO fallback.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..run import Run
from ..vo.calib import CalibrationError, RectifiedRig
from ..vo.frontend import FrontEndParams, FrontEndResult, SensorAids, run_frontend
from ..vo.geometry import invert, make_transform, pose_to_2d
from .kitti import read_image

__all__ = ["EurocParams", "CameraYaml", "read_sensor_yaml", "euroc_rig", "quat_to_matrix",
           "euroc_frontend", "load_euroc"]


@dataclass(frozen=True)
class EurocParams:
    """max_frames: process at most this many frames; height: metres from body to ground
    (None: ground-truth z at frame 0, else 0); gravity_window: seconds of IMU after the first
    frame averaged to find "up"."""

    max_frames: int | None = None
    height: float | None = None
    gravity_window: float = 0.1
    frontend: FrontEndParams = field(default_factory=FrontEndParams)


@dataclass(frozen=True)
class CameraYaml:
    k: np.ndarray
    dist: np.ndarray
    t_bs: np.ndarray
    size: tuple[int, int]


def _numbers(fs: cv2.FileStorage, key: str, count: int, path: Path) -> np.ndarray:
    node = fs.getNode(key)
    if node.empty() or node.isNone():
        raise CalibrationError(f"{path}: missing field '{key}'")
    if key == "T_BS":
        node = node.getNode("data")
        if node.empty():
            raise CalibrationError(f"{path}: missing field 'T_BS.data'")
    vals = [node.at(i).real() for i in range(node.size())] if node.isSeq() else []
    if len(vals) != count:
        raise CalibrationError(f"{path}: field '{key}' has {len(vals)} numbers, expected {count}")
    return np.array(vals, dtype=np.float64)


def read_sensor_yaml(path: Path) -> CameraYaml:
    """Intrinsics (fu, fv, cu, cv), radial-tangential distortion, T_BS and resolution."""
    if not path.is_file():
        raise CalibrationError(f"{path}: calibration file is missing")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise CalibrationError(f"{path}: not a readable YAML file")
    model = fs.getNode("distortion_model").string()
    if model and model != "radial-tangential":
        raise CalibrationError(f"{path}: field 'distortion_model': {model!r} is not supported")
    fu, fv, cu, cv = _numbers(fs, "intrinsics", 4, path)
    dist = _numbers(fs, "distortion_coefficients", 4, path)
    t_bs = _numbers(fs, "T_BS", 16, path).reshape(4, 4)
    w, h = _numbers(fs, "resolution", 2, path)
    fs.release()
    k = np.array([[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]])
    return CameraYaml(k, dist, t_bs, (int(w), int(h)))


def euroc_rig(cam0: CameraYaml, cam1: CameraYaml) -> RectifiedRig:
    """Rectified rig from the two cameras' calibration (pose of cam0 in cam1 from the T_BS)."""
    if cam0.size != cam1.size:
        raise CalibrationError(f"cam0 is {cam0.size} but cam1 is {cam1.size}")
    t_10 = invert(cam1.t_bs) @ cam0.t_bs
    return RectifiedRig.from_raw(cam0.k, cam0.dist, cam1.k, cam1.dist, t_10[:3, :3], t_10[:3, 3],
                                 cam0.size)


def quat_to_matrix(q_wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion (w, x, y, z)."""
    w, x, y, z = np.asarray(q_wxyz, dtype=np.float64) / np.linalg.norm(q_wxyz)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _frames(cam_dir: Path) -> tuple[np.ndarray, list[Path]]:
    csv = cam_dir / "data.csv"
    if not csv.is_file():
        raise FileNotFoundError(f"{csv}: missing frame list")
    rows = [line.split(",") for line in csv.read_text().splitlines()
            if line.strip() and not line.startswith("#")]
    return (np.array([int(r[0]) for r in rows], np.int64),
            [cam_dir / "data" / r[1].strip() for r in rows])


def _robot_from_body(up_b: np.ndarray, fwd_b: np.ndarray, height: float) -> np.ndarray:
    """T_body_robot: robot axes (x forward, y left, z up) in the body frame, origin on the ground."""
    up = up_b / np.linalg.norm(up_b)
    fwd = fwd_b - up * (fwd_b @ up)
    fwd /= np.linalg.norm(fwd)
    return make_transform(np.column_stack([fwd, np.cross(up, fwd), up]), -height * up)


def euroc_frontend(root: str | Path, params: EurocParams = EurocParams()) -> FrontEndResult:
    """Run the stereo front-end over an EuRoC ASL folder (``root`` holds ``mav0``)."""
    mav = Path(root) / "mav0" if (Path(root) / "mav0").is_dir() else Path(root)
    cam0, cam1 = (read_sensor_yaml(mav / c / "sensor.yaml") for c in ("cam0", "cam1"))
    rig = euroc_rig(cam0, cam1)
    ts0, left = _frames(mav / "cam0")
    ts1, right = _frames(mav / "cam1")
    n = min(len(ts0), len(ts1))
    if params.max_frames is not None:
        n = min(n, params.max_frames)
    if not np.array_equal(ts0[:n], ts1[:n]):
        bad = int(np.argmax(ts0[:n] != ts1[:n]))
        raise ValueError(f"{mav}: cam0 and cam1 timestamps differ at frame {bad}")
    ts = ts0[:n]
    imu_csv = mav / "imu0" / "data.csv"
    if not imu_csv.is_file():
        raise FileNotFoundError(f"{imu_csv}: missing (needed for the gravity direction)")
    imu = np.loadtxt(imu_csv, delimiter=",", comments="#", ndmin=2)
    imu_t, gyro, acc = imu[:, 0].astype(np.int64), imu[:, 1:4], imu[:, 4:7]
    first = (imu_t >= ts[0]) & (imu_t <= ts[0] + int(params.gravity_window * 1e9))
    if not first.any():
        raise ValueError(f"{imu_csv}: no IMU samples within {params.gravity_window} s of frame 0")
    up_b = acc[first].mean(axis=0)

    gt_csv = mav / "state_groundtruth_estimate0" / "data.csv"
    gt_body = None
    if gt_csv.is_file():
        g = np.loadtxt(gt_csv, delimiter=",", comments="#", ndmin=2)
        idx = np.clip(np.searchsorted(g[:, 0], ts), 0, len(g) - 1)
        idx = np.where(np.abs(g[np.maximum(idx - 1, 0), 0] - ts) < np.abs(g[idx, 0] - ts),
                       np.maximum(idx - 1, 0), idx)
        if np.abs(g[idx, 0] - ts).max() < 5e6:  # every frame has a ground-truth row within 5 ms
            gt_body = [make_transform(quat_to_matrix(r[4:8]), r[1:4]) for r in g[idx]]
    height = params.height if params.height is not None else (
        gt_body[0][2, 3] if gt_body is not None else 0.0)
    t_body_robot = _robot_from_body(up_b, cam0.t_bs[:3, 2], height)
    t_raw_rect = make_transform(rig.r_left.T, np.zeros(3))
    t_robot_cam = invert(t_body_robot) @ cam0.t_bs @ t_raw_rect
    gt = None if gt_body is None else np.stack([pose_to_2d(b @ t_body_robot) for b in gt_body])

    # Per frame: mean specific force and yaw increment (gyro about "up") since the last frame.
    r_rb = t_body_robot[:3, :3].T
    accel, yaw = np.zeros((n, 3)), np.zeros(n)
    edges = np.searchsorted(imu_t, ts, side="right")
    for t in range(n):
        lo = edges[t - 1] if t else max(edges[0] - 1, 0)
        sel = slice(lo, max(edges[t], lo + 1))
        accel[t] = r_rb @ acc[sel].mean(axis=0)
        if t:
            dt = np.diff(imu_t[lo - 1:edges[t]]) * 1e-9 if lo > 0 else np.zeros(0)
            w_up = (gyro[lo:edges[t]] @ t_body_robot[:3, 2])[:len(dt)]
            yaw[t] = float(np.sum(w_up * dt))

    def load(t: int) -> tuple[np.ndarray, np.ndarray]:
        return read_image(left[t]), read_image(right[t])

    return run_frontend(load, n, rig, t_robot_cam, (ts - ts[0]) * 1e-9, params.frontend,
                        aids=SensorAids(imu_yaw=yaw, accel=accel), ground_truth=gt,
                        initial_pose=None if gt is None else gt[0], source=str(mav))


def load_euroc(root: str | Path, params: EurocParams = EurocParams()) -> Run:
    """The Run of an EuRoC ASL sequence (see :func:`euroc_frontend` for the summary)."""
    return euroc_frontend(root, params).run
