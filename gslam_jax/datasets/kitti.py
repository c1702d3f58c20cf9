"""KITTI odometry adapter: ``sequences/NN/{image_0,image_1,calib.txt,times.txt}``, ``poses/NN.txt``.

Images are already rectified (``P0``/``P1`` in calib.txt). The camera (x right, y down,
z forward) is mounted ``camera_height`` metres above the ground and level by default (KITTI's
car, 1.65 m); the config's [rig] changes the mount (``datasets.mount.camera_mount``). Ground
truth (camera-0-to-world 3x4 per frame, world = camera 0 at frame 0) is moved into the robot
frame through the same mount and projected to (x, y, yaw) like the VO path. Without
``times.txt`` frames are 0.1 s apart. Image ``NNNNNN.png`` is frame NNNNNN and takes line
NNNNNN (from 0) of times.txt and the poses file; frames must be consecutive, a gap is an error
naming the missing image.

The way back, for KITTI's evaluation tools: :func:`camera_poses` turns a planar robot path into
camera-0-to-world poses in the frame of ``poses/NN.txt`` (:class:`KittiFrame`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np

from gslam_jax.config import Config
from gslam_jax.datasets.mount import camera_mount
from gslam_jax.datasets.reading import first_not_increasing, pose_jump, read_image, read_table
from gslam_jax.datasets.registry import DataSource, LoadedSource, Source, stereo_settings
from gslam_jax.errors import DatasetError
from gslam_jax.run import Run
from gslam_jax.vo.calib import CalibrationError, ImageError, RectifiedRig
from gslam_jax.vo.frontend import FrontEndParams, FrontEndResult, run_frontend
from gslam_jax.vo.geometry import CAM_TO_ROBOT_AXES, invert, make_transform, pose_to_2d
from gslam_jax.vo.localmap import localmap_params
from gslam_jax.vo.stereo import DenseStereoParams

__all__ = ["KittiParams", "KittiFrame", "find_sequence", "read_kitti_calib", "read_kitti_poses",
           "robot_from_camera", "kitti_frame", "off_plane", "camera_poses", "kitti_frontend",
           "load_kitti"]


@dataclass(frozen=True)
class KittiParams:
    """sequence: folder name under ``sequences/`` (and ``poses/<sequence>.txt``); None picks the
    only one. max_frames: process at most this many frames (None: all). The dense stereo search
    range comes from the calibration (``vo.stereo.with_calibrated_range``: depths from 3 m on,
    as for any stereo folder): KITTI's fx * baseline of 380 px m gives 128 disparities, where
    the generic default 64 would cover depths from 5.9 m only and nearer surfaces (parked cars)
    would be matched wrongly as far points. mount: the 4x4 camera-0-to-robot
    transform (None: level, ``camera_height`` above the ground; see :func:`robot_from_camera`)."""

    sequence: str | None = None
    camera_height: float = 1.65
    mount: np.ndarray | None = None
    frame_period: float = 0.1
    max_frames: int | None = None
    frontend: FrontEndParams = field(default_factory=lambda: FrontEndParams(
        stereo=DenseStereoParams(num_disparities=0)))


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
        bad = np.flatnonzero(~np.isfinite(fields[key]))
        if bad.size:
            raise CalibrationError(f"{path}: field '{key}' number {bad[0] + 1} of 12 is "
                                   f"{fields[key][bad[0]]} (a projection matrix must be finite)")
    return RectifiedRig.from_projections(fields["P0"], fields["P1"], size, str(path))


def read_kitti_poses(path: Path) -> np.ndarray:
    """[T, 4, 4] camera-to-world ground-truth poses (line i: frame i)."""
    data = read_table(path, 12).data
    out = np.tile(np.eye(4), (len(data), 1, 1))
    out[:, :3, :] = data.reshape(-1, 3, 4)
    return out


class KittiFrame(NamedTuple):
    """Where a KITTI run's robot frame sits in KITTI's: ``t_robot_cam`` (4x4, camera 0 to
    robot, the mount the adapter used), ``first_camera`` (4x4, ``poses/NN.txt``'s pose of
    the run's first frame; the identity without a poses file) and ``off_plane`` ([T, 4, 4] or
    None: what the VO's 6-DoF pose of each frame adds to its planar projection, its height,
    roll and pitch, :func:`off_plane`; None: level, at the first frame's height)."""

    t_robot_cam: np.ndarray
    first_camera: np.ndarray
    off_plane: np.ndarray | None = None


def _planar_matrix(path: np.ndarray) -> np.ndarray:
    """[T, 4, 4] of planar poses [T, 3] (x, y, yaw; z = 0, level)."""
    out = np.tile(np.eye(4), (len(path), 1, 1))
    c, s = np.cos(path[:, 2]), np.sin(path[:, 2])
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = c, -s, s, c
    out[:, 0, 3], out[:, 1, 3] = path[:, 0], path[:, 1]
    return out


def off_plane(poses: np.ndarray) -> np.ndarray:
    """[T, 4, 4] ``inv(P_t) W_t`` of 6-DoF robot poses ``W_t`` [T, 4, 4] (z up) and their planar
    projections ``P_t`` (``pose_to_2d``): a height (translation (0, 0, z)) and a tilt (roll
    and pitch, no yaw). The part of the VO's motion that the filter's planar path lacks."""
    poses = np.asarray(poses, np.float64)
    planar = _planar_matrix(np.stack([pose_to_2d(w) for w in poses]))
    return np.stack([invert(p) @ w for p, w in zip(planar, poses)])


def robot_from_camera(params: KittiParams) -> np.ndarray:
    """4x4 camera-0-to-robot transform: ``params.mount``, or by default KITTI's camera axes
    turned into the robot's (x forward, y left, z up), ``params.camera_height`` above the
    ground, level."""
    if params.mount is not None:
        return np.array(params.mount, np.float64)
    return make_transform(CAM_TO_ROBOT_AXES, [0.0, 0.0, params.camera_height])


def kitti_frame(root: str | Path, params: KittiParams = KittiParams()) -> KittiFrame:
    """The KittiFrame of the frames ``kitti_frontend(root, params)`` reads."""
    seq = find_sequence(Path(root), params.sequence)
    first = int(_check_frames(seq, params.max_frames)[0].stem)
    pose_file = Path(root) / "poses" / f"{seq.name}.txt"
    cam = read_kitti_poses(pose_file)[first] if pose_file.is_file() else np.eye(4)
    return KittiFrame(robot_from_camera(params), cam)


def camera_poses(path: np.ndarray, start: np.ndarray, frame: KittiFrame) -> np.ndarray:
    """[T, 4, 4] camera-0-to-world poses in KITTI's frame (that of ``poses/NN.txt``) of a
    planar robot ``path`` [T, 3] whose world is the robot frame at ``start`` (the Run's start
    pose): the inverse of the adapter's change of the ground truth into the robot frame,
    ``C_t = first_camera inv(T_rc) inv(S) P_t T_rc`` with P_t, S the planar poses as 4x4 (z = 0)
    and T_rc = ``t_robot_cam``. What the planar path lacks (height, pitch, roll) is the VO's,
    ``P_t`` followed by ``frame.off_plane[t]``, where the frame has it; else that of the mount
    (level, at the first camera's height)."""
    path = np.asarray(path, np.float64)
    planar = _planar_matrix(path)
    if frame.off_plane is not None:
        if len(frame.off_plane) != len(path):
            raise ValueError(f"off_plane has {len(frame.off_plane)} poses, the path {len(path)}")
        planar = planar @ frame.off_plane
    x, y, th = np.asarray(start, np.float64)
    s0 = make_transform([[np.cos(th), -np.sin(th), 0.0], [np.sin(th), np.cos(th), 0.0],
                         [0.0, 0.0, 1.0]], [x, y, 0.0])
    t_rc = frame.t_robot_cam
    return frame.first_camera @ invert(t_rc) @ invert(s0) @ planar @ t_rc


def _dataset_root_hint(root: Path) -> str:
    """Where a ``root`` without ``sequences/`` lies: inside a KITTI odometry folder (e.g. at
    ``sequences/00`` or ``poses``: its root and sequence to give instead), or at an EuRoC
    folder; '' when neither."""
    here = root.absolute()
    for up in here.parents[:4]:
        if (up / "sequences").is_dir():
            rel = here.relative_to(up).parts
            seq = f" --sequence {rel[1]}" if len(rel) > 1 and rel[0] == "sequences" else ""
            return f"; it lies inside the KITTI odometry folder {up}: give --path {up}{seq}"
    if (root / "mav0").is_dir() or root.name == "mav0":
        return "; it looks like an EuRoC folder (mav0): --source euroc"
    return ""


def find_sequence(root: Path, sequence: str | None) -> Path:
    """The folder ``root/sequences/<sequence>``; with ``sequence`` None, the only folder there
    (none or several: a DatasetError listing them, asking for ``--sequence NN`` /
    ``KittiParams(sequence=...)``). A sequence that is not there is a FileNotFoundError listing
    those that are; a ``root`` inside a KITTI folder one suggesting its root."""
    root = Path(root)
    seqs = root / "sequences"
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such folder")
    if not seqs.is_dir():
        raise FileNotFoundError(f"{root}: no 'sequences' folder (expected the KITTI odometry "
                                f"layout, DIR/sequences/NN/image_0/...){_dataset_root_hint(root)}")
    found = sorted(p.name for p in seqs.iterdir() if p.is_dir())
    if sequence is None:
        if not found:
            raise DatasetError(f"{seqs}: no sequence folders")
        if len(found) > 1:
            raise DatasetError(f"{seqs}: holds sequences {', '.join(found)}; choose one "
                               "(--sequence NN, or KittiParams(sequence=...))")
        sequence = found[0]
    path = seqs / sequence
    if not path.is_dir():
        held = f"holds {', '.join(found)}" if found else "holds no sequence folders"
        raise FileNotFoundError(f"{path}: no such sequence; {seqs} {held}")
    return path


def _numbered_images(folder: Path) -> list[tuple[int, Path]]:
    """(frame number, path) of the ``NNNNNN.png`` images in a folder, by frame number."""
    out = []
    for path in folder.glob("*.png"):
        if not (path.stem.isascii() and path.stem.isdigit()):
            raise ImageError(f"{path}: file name is not a frame number (expected NNNNNN.png)")
        out.append((int(path.stem), path))
    out.sort()
    for (a, pa), (b, pb) in zip(out, out[1:]):
        if a == b:
            raise ImageError(f"{pb}: same frame number as {pa.name}")
    return out


def _check_frames(seq: Path, max_frames: int | None) -> list[Path]:
    """The left images to process: consecutive frame numbers (image_1 may not hold frames that
    image_0 lacks). ImageError naming the first missing file."""
    left_dir = seq / "image_0"
    found = _numbered_images(left_dir)
    if not found:
        raise FileNotFoundError(f"{left_dir}: no .png images")
    if max_frames is not None and max_frames < 1:
        raise DatasetError(f"max_frames must be at least 1, got {max_frames}")
    used = found if max_frames is None else found[:max_frames]
    first, width = used[0][0], len(used[0][1].stem)
    for i, (k, _) in enumerate(used):
        if k != first + i:
            raise ImageError(f"{left_dir / f'{first + i:0{width}d}.png'}: missing "
                             "(frames must be consecutive)")
    last = used[-1][0] if len(used) < len(found) else None
    have = {k for k, _ in used}
    for k, right in _numbered_images(seq / "image_1"):
        if k not in have and (last is None or k <= last):
            raise ImageError(f"{left_dir / right.name}: missing (image_1 has it; frames must be "
                             "consecutive)")
    return [p for _, p in used]


def kitti_frontend(root: str | Path, params: KittiParams = KittiParams(), *,
                   progress: Callable[[int, int], None] | None = None,
                   frame_turn: float = 0.0) -> FrontEndResult:
    """Run the stereo front-end over a KITTI odometry sequence; returns Run, summary and poses.
    ``progress(done, total)`` follows the frames. ``frame_turn``: radians by which the world
    frame (the robot frame at frame 0) is turned, the ground truth and start pose with it, so
    that local maps on the map's lattice (``[localmap] lattice = "map"``) are built for that
    frame (the frame-orientation check, ``experiments.frame_lattice``).

    Frame numbers come from the image names (``NNNNNN.png``, consecutive); frame k takes line k of
    times.txt and of the poses file. Missing or out-of-order rows are named errors.
    """
    root = Path(root)
    seq = find_sequence(root, params.sequence)
    lefts = _check_frames(seq, params.max_frames)
    frames = np.array([int(p.stem) for p in lefts])
    n = len(lefts)
    times_file = seq / "times.txt"
    if times_file.is_file():
        table = read_table(times_file, 1)
        if len(table.data) <= frames[-1]:
            raise DatasetError(f"{times_file}: {len(table.data)} times for frames up to "
                               f"{lefts[-1].name} (one line per frame from frame 0)")
        times, lines = table.data[frames, 0], table.lines[frames]
        i = first_not_increasing(times)
        if i is not None:
            raise DatasetError(f"{times_file}:{lines[i]}: time {times[i]} of frame {lefts[i].name} "
                               f"is not after {times[i - 1]} (times must increase)")
    else:
        times = np.arange(n) * params.frame_period
    pose_file = root / "poses" / f"{seq.name}.txt"
    cams = None
    if pose_file.is_file():
        cams = read_kitti_poses(pose_file)
        if len(cams) <= frames[-1]:
            raise DatasetError(f"{pose_file}: {len(cams)} poses for frames up to {lefts[-1].name} "
                               "(one line per frame from frame 0)")
        cams = cams[frames]
    first = read_image(lefts[0])
    rig = read_kitti_calib(seq / "calib.txt", (first.shape[1], first.shape[0]))
    t_robot_cam = robot_from_camera(params)
    gt = None
    if cams is not None:
        rel = invert(cams[0])  # world = robot frame at frame 0
        gt = np.stack([pose_to_2d(t_robot_cam @ rel @ c @ invert(t_robot_cam)) for c in cams])
        if frame_turn:
            c_, s_ = np.cos(frame_turn), np.sin(frame_turn)
            gt = np.stack([c_ * gt[:, 0] - s_ * gt[:, 1], s_ * gt[:, 0] + c_ * gt[:, 1],
                           np.angle(np.exp(1j * (gt[:, 2] + frame_turn)))], axis=1)

    def load(t: int) -> tuple[np.ndarray, np.ndarray]:
        return read_image(lefts[t]), read_image(seq / "image_1" / lefts[t].name)

    return run_frontend(load, n, rig, t_robot_cam, times, params.frontend, ground_truth=gt,
                        initial_pose=(gt[0] if gt is not None else
                                      np.array([0.0, 0.0, frame_turn]) if frame_turn else None),
                        source=str(seq),
                        progress=progress)


def load_kitti(root: str | Path, params: KittiParams = KittiParams()) -> Run:
    """The Run of a KITTI odometry sequence (see :func:`kitti_frontend` for the summary)."""
    return kitti_frontend(root, params).run


def _load(src: Source, config: Config, progress: Callable[[int, int], None] | None = None
          ) -> LoadedSource:
    sequence = find_sequence(Path(src.path), src.sequence).name
    fe = KittiParams().frontend  # KITTI's own front-end defaults, with the config's settings
    mount = camera_mount(config, robot_from_camera(KittiParams()), f"--source kitti {src.path}")
    params = KittiParams(
        sequence=sequence, max_frames=src.max_frames, mount=mount,
        frontend=replace(fe, local_map=localmap_params(config, "stereo"),
                         on_bad_frame=src.on_bad_frame,
                         stereo=stereo_settings(config, fe.stereo)))
    result = kitti_frontend(src.path, params, progress=progress)
    print(result.summary.text())
    pose_file = Path(src.path) / "poses" / f"{sequence}.txt"
    if pose_file.is_file():  # the ground truth of the frames read
        frames = [int(p.stem) for p in _check_frames(find_sequence(Path(src.path), sequence),
                                                      src.max_frames)]
        table = read_table(pose_file, 12)
        jump = pose_jump(table.data[frames][:, [3, 7, 11]], table.lines[frames], pose_file)
        if jump is not None:
            print(f"note: {jump}, as the ground truth that scores this run")
    frame = kitti_frame(src.path, params)._replace(off_plane=off_plane(result.poses))
    return LoadedSource(result.run, f"KITTI {src.path} sequence {sequence}", kitti_frame=frame)


SOURCE = DataSource(name="kitti", help="KITTI odometry layout (sequences/NN, poses/NN.txt)",
                    load=_load, images=True, path="the KITTI odometry folder, holding "
                    "sequences/", sequence=True)
