"""KITTI odometry adapter: ``sequences/NN/{image_0,image_1,calib.txt,times.txt}``, ``poses/NN.txt``.

Images are already rectified (``P0``/``P1`` in calib.txt). The camera (x right, y down,
z forward) is mounted ``camera_height`` metres above the ground and assumed level; ground truth
(camera-0-to-world 3x4 per frame, world = camera 0 at frame 0) is moved into the robot frame
and projected to (x, y, yaw) like the VO path. Without ``times.txt`` frames are 0.1 s apart.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..run import Run
from ..vo.calib import CalibrationError, ImageError, RectifiedRig
from ..vo.frontend import FrontEndParams, FrontEndResult, run_frontend
from ..vo.geometry import CAM_TO_ROBOT_AXES, invert, make_transform, pose_to_2d

__all__ = ["KittiParams", "read_kitti_calib", "read_kitti_poses", "read_image", "kitti_frontend",
           "load_kitti"]


@dataclass(frozen=True)
class KittiParams:
    """sequence: folder name under ``sequences/`` (and ``poses/<sequence>.txt``); None picks the
    only one. max_frames: process at most this many frames (None: all)."""

    sequence: str | None = None
    camera_height: float = 1.65
    frame_period: float = 0.1
    max_frames: int | None = None
    frontend: FrontEndParams = field(default_factory=FrontEndParams)


def read_image(path: Path) -> np.ndarray:
    """Grey image or ImageError naming the file."""
    if not path.is_file():
        raise ImageError(f"{path}: image file is missing")
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise ImageError(f"{path}: not a readable image (corrupt or unknown format)")
    return img


def read_kitti_calib(path: Path, size: tuple[int, int]) -> RectifiedRig:
    """Parse ``P0:`` and ``P1:`` (12 numbers each) from a KITTI calib.txt."""
    if not path.is_file():
        raise CalibrationError(f"{path}: calibration file is missing")
    fields: dict[str, np.ndarray] = {}
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if ":" not in line:
            continue
        key, _, rest = line.partition(":")
        try:
            fields[key.strip()] = np.array(rest.split(), dtype=np.float64)
        except ValueError as err:
            raise CalibrationError(f"{path}:{n}: field '{key.strip()}': {err}") from err
    for key in ("P0", "P1"):
        if key not in fields:
            raise CalibrationError(f"{path}: missing field '{key}' (3x4 projection matrix)")
        if fields[key].size != 12:
            raise CalibrationError(f"{path}: field '{key}' has {fields[key].size} numbers, "
                                   "expected 12")
    return RectifiedRig.from_projections(fields["P0"], fields["P1"], size, str(path))


def read_kitti_poses(path: Path) -> np.ndarray:
    """[T, 4, 4] camera-to-world ground-truth poses."""
    data = np.loadtxt(path, ndmin=2)
    if data.shape[1] != 12:
        raise ValueError(f"{path}: expected 12 numbers per line, got {data.shape[1]}")
    out = np.tile(np.eye(4), (len(data), 1, 1))
    out[:, :3, :] = data.reshape(-1, 3, 4)
    return out


def _sequence_dir(root: Path, sequence: str | None) -> Path:
    seqs = root / "sequences"
    if not seqs.is_dir():
        raise FileNotFoundError(f"{root}: no 'sequences' folder (expected the KITTI odometry layout)")
    if sequence is None:
        found = sorted(p.name for p in seqs.iterdir() if p.is_dir())
        if len(found) != 1:
            raise ValueError(f"{seqs}: holds {found}; pass KittiParams(sequence=...)")
        sequence = found[0]
    path = seqs / sequence
    if not path.is_dir():
        raise FileNotFoundError(f"{path}: no such sequence")
    return path


def kitti_frontend(root: str | Path, params: KittiParams = KittiParams()) -> FrontEndResult:
    """Run the stereo front-end over a KITTI odometry sequence; returns Run, summary and poses."""
    root = Path(root)
    seq = _sequence_dir(root, params.sequence)
    lefts = sorted((seq / "image_0").glob("*.png"))
    if not lefts:
        raise FileNotFoundError(f"{seq / 'image_0'}: no .png images")
    if params.max_frames is not None:
        lefts = lefts[:params.max_frames]
    first = read_image(lefts[0])
    rig = read_kitti_calib(seq / "calib.txt", (first.shape[1], first.shape[0]))
    t_robot_cam = make_transform(CAM_TO_ROBOT_AXES, [0.0, 0.0, params.camera_height])
    n = len(lefts)
    times_file = seq / "times.txt"
    times = (np.loadtxt(times_file, ndmin=1)[:n] if times_file.is_file()
             else np.arange(n) * params.frame_period)
    gt = None
    pose_file = root / "poses" / f"{seq.name}.txt"
    if pose_file.is_file():
        cams = read_kitti_poses(pose_file)[:n]
        if len(cams) != n:
            raise ValueError(f"{pose_file}: {len(cams)} poses for {n} frames")
        rel = invert(cams[0])  # world = robot frame at frame 0
        gt = np.stack([pose_to_2d(t_robot_cam @ rel @ c @ invert(t_robot_cam)) for c in cams])

    def load(t: int) -> tuple[np.ndarray, np.ndarray]:
        return read_image(lefts[t]), read_image(seq / "image_1" / lefts[t].name)

    return run_frontend(load, n, rig, t_robot_cam, times, params.frontend, ground_truth=gt,
                        initial_pose=None if gt is None else gt[0], source=str(seq))


def load_kitti(root: str | Path, params: KittiParams = KittiParams()) -> Run:
    """The Run of a KITTI odometry sequence (see :func:`kitti_frontend` for the summary)."""
    return kitti_frontend(root, params).run
