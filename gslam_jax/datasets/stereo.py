"""Generic stereo source (``--source stereo --path DIR``): a folder of image pairs from one's own
rig, its calibration, and the camera mount from the config's [rig].

Layout (docs/formats.md):

- ``DIR/left/*`` and ``DIR/right/*`` (or ``DIR/image_0``, ``DIR/image_1`` as KITTI names them):
  grey or colour images (png, jpg, pgm, bmp, tif), one pair per file name, in natural order of
  the names (``frame2`` before ``frame10``). A file without its partner is an error naming it.
- ``DIR/calib.yaml`` (OpenCV FileStorage or ROS camera_info YAML; :func:`read_calib_yaml`) or
  ``DIR/calib.txt`` (KITTI: rectified ``P0:``/``P1:`` projections).
- optional ``DIR/times.txt``: one time a pair (seconds, increasing), else ``frame_period``
  apart from 0. Run times start at 0; a first time other than 0 becomes ``Run.time_origin_ns``,
  so the outputs carry the folder's clock.
- optional ``DIR/odometry.txt`` (wheel odometry) and ``DIR/groundtruth.txt``: TUM lines
  ``time x y z qx qy qz qw`` of the robot (x forward, y left, z up) in a z-up world, on the
  clock of times.txt. Each is read at the frames' times, linearly between the two rows around
  a frame (NaN outside the file's span or across a gap of more than ``max_gap`` seconds). The
  odometry's increments are the fallback where VO fails; the ground truth (in its own world
  frame, where the run then starts) scores the run.

The mount (``StereoParams.mount``; from the command line [rig] through
``datasets.mount.camera_mount``) places the left camera, as it sits on the robot (unrectified),
in the robot frame; the rectifying rotation of the calibration is added to it. There is no
default: [rig] must give ``height`` (and ``pitch``, ...) or ``matrix``.
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from gslam_jax.config import Config
from gslam_jax.datasets.calib_yaml import field_node, numbers, open_yaml, text
from gslam_jax.datasets.kitti import read_kitti_calib
from gslam_jax.datasets.mount import camera_mount
from gslam_jax.datasets.reading import first_not_increasing, read_image, read_table
from gslam_jax.datasets.registry import DataSource, LoadedSource, Source, stereo_settings
from gslam_jax.errors import DatasetError
from gslam_jax.vo.calib import CalibrationError, CameraModel, ImageError, RectifiedRig
from gslam_jax.vo.frontend import FrontEndParams, FrontEndResult, SensorAids, run_frontend
from gslam_jax.vo.geometry import increments_2d, make_transform
from gslam_jax.vo.localmap import localmap_params
from gslam_jax.vo.stereo import DenseStereoParams

__all__ = ["StereoParams", "LAYOUTS", "IMAGE_SUFFIXES", "find_pairs", "read_calib_yaml",
           "read_stereo_calib", "read_tum_poses", "poses_at", "stereo_frontend"]

LAYOUTS = (("left", "right"), ("image_0", "image_1"))  # the first is the primary layout
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pgm", ".ppm", ".bmp", ".tif", ".tiff")
MAX_BASELINE = 5.0  # metres; beyond it a calibration is likely in millimetres


@dataclass(frozen=True)
class StereoParams:
    """mount: 4x4 left-camera-to-robot transform (the raw camera; see the module docstring).
    max_frames: the first pairs only (None: all); the dense stereo search range comes from the
    calibration unless ``frontend.stereo.num_disparities`` gives one
    (``vo.stereo.with_calibrated_range``, the same rule as the KITTI reader's); frame_period: seconds between pairs without
    times.txt; max_gap: seconds between the odometry or ground-truth rows around a frame beyond
    which that frame has none."""

    mount: np.ndarray
    max_frames: int | None = None
    frame_period: float = 0.1
    max_gap: float = 1.0
    frontend: FrontEndParams = field(default_factory=lambda: FrontEndParams(
        stereo=DenseStereoParams(num_disparities=0)))


def _natural(name: str) -> list:
    """Sort key: digit runs as numbers ('frame2' before 'frame10')."""
    return [(0, int(p), p) if p.isdigit() else (1, 0, p) for p in re.split(r"(\d+)", name)]


def _images(folder: Path) -> dict[str, Path]:
    return {p.name: p for p in folder.iterdir()
            if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".")}


def find_pairs(root: Path) -> list[tuple[Path, Path]]:
    """The (left, right) image paths of the folder, in natural order of the file names.

    FileNotFoundError for a missing folder or layout (naming what is expected, and the source
    of a KITTI or EuRoC folder); DatasetError for a folder holding both layouts; ImageError
    naming an image whose partner is missing."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such folder")
    present = [(l, r) for l, r in LAYOUTS if (root / l).is_dir() or (root / r).is_dir()]
    if len(present) > 1:
        raise DatasetError(f"{root}: holds both {present[0][0]}/ {present[0][1]}/ and "
                           f"{present[1][0]}/ {present[1][1]}/ image folders; which pairs to "
                           "read is ambiguous: keep one layout (move the other out)")
    for left_name, right_name in present:
        left_dir, right_dir = root / left_name, root / right_name
        break
    else:
        hint = ("; it looks like a KITTI odometry folder (sequences/): --source kitti"
                if (root / "sequences").is_dir() else
                "; it looks like an EuRoC folder (mav0): --source euroc"
                if (root / "mav0").is_dir() else "")
        raise FileNotFoundError(f"{root}: no 'left' and 'right' image folders (expected "
                                "DIR/left/*.png and DIR/right/*.png, or DIR/image_0 and "
                                f"DIR/image_1){hint}")
    for folder in (left_dir, right_dir):
        if not folder.is_dir():
            raise FileNotFoundError(f"{folder}: no such folder (the stereo partner of "
                                    f"{(right_dir if folder == left_dir else left_dir).name}/)")
    lefts, rights = _images(left_dir), _images(right_dir)
    if not lefts:
        raise FileNotFoundError(f"{left_dir}: no images ({', '.join(IMAGE_SUFFIXES)})")
    for names, here, other in ((lefts, left_dir, right_dir), (rights, right_dir, left_dir)):
        lone = sorted(set(names) - set(lefts if here == right_dir else rights), key=_natural)
        if lone:
            more = f" (and {len(lone) - 1} more)" if len(lone) > 1 else ""
            raise ImageError(f"{other / lone[0]}: missing, the partner of {here / lone[0]}"
                             f"{more}; pairs are matched by file name")
    return [(lefts[n], rights[n]) for n in sorted(lefts, key=_natural)]


def _matrix(node, names: tuple[str, ...], shape: tuple[int, int], path: Path,
            prefix: str = "", default: np.ndarray | None = None) -> np.ndarray:
    child, name = field_node(node, names)
    if child is None and default is not None:
        return default
    return numbers(child, prefix + name, shape[0] * shape[1], path).reshape(shape)


def _size(node, path: Path, prefix: str = "") -> tuple[int, int] | None:
    """(width, height) of ``width``/``image_width`` and ``height``/``image_height``, or None
    where neither is given."""
    found = [field_node(node, (k, f"image_{k}")) for k in ("width", "height")]
    if all(child is None for child, _ in found):
        return None
    out = []
    for child, name in found:
        if child is None:
            raise CalibrationError(f"{path}: missing field '{prefix}{name}' (the other image "
                                   "dimension is given)")
        v = child.real() if child.isInt() or child.isReal() else float("nan")
        if not (v > 0 and v == int(v)):
            raise CalibrationError(f"{path}: field '{prefix}{name}' must be a positive integer "
                                   "(pixels)")
        out.append(int(v))
    return out[0], out[1]


def _camera(node, side: str, path: Path, size: tuple[int, int]) -> CameraModel:
    """One camera of the per-camera form (ROS camera_info names or K, D, R, P)."""
    prefix = f"{side}."
    k = _matrix(node, ("K", "camera_matrix"), (3, 3), path, prefix)
    p = _matrix(node, ("P", "projection_matrix"), (3, 4), path, prefix)
    r = _matrix(node, ("R", "rectification_matrix"), (3, 3), path, prefix, default=np.eye(3))
    child, name = field_node(node, ("D", "distortion_coefficients"))
    d = np.zeros(0) if child is None else numbers(child, prefix + name, None, path)
    model = text(field_node(node, ("distortion_model",))[0]) or "plumb_bob"
    own = _size(node, path, prefix)
    if own is not None and own != size:
        raise CalibrationError(f"{path}: field '{side}' image size {own[0]}x{own[1]} differs "
                               f"from the images' {size[0]}x{size[1]}")
    return CameraModel(k, d, r, p, size, model)


def read_calib_yaml(path: Path, size: tuple[int, int]) -> RectifiedRig:
    """The rectified rig of a calib.yaml for images of ``size`` (width, height); two forms:

    - per camera: maps ``left`` and ``right``, each with ``K`` (or ``camera_matrix``), ``D``
      (``distortion_coefficients``; absent: none), ``R`` (``rectification_matrix``; absent: the
      identity), ``P`` (``projection_matrix``; the right one's ``P[0, 3]`` is ``-fx * baseline``),
      ``distortion_model`` (plumb_bob, rational_polynomial or equidistant; absent: plumb_bob)
      and ``width``/``height`` (``image_width``/``image_height``; optional): the ROS
      camera_info fields, as ``camera_calibration`` writes them (-> ``from_rectification``);
    - a stereo extrinsic, as ``cv2.stereoCalibrate`` gives it: ``K1``/``M1``, ``D1``,
      ``K2``/``M2``, ``D2`` of the raw cameras and ``R``, ``T``, the pose of the left camera in
      the right one (X_right = R X_left + T, metres) (-> ``from_raw``, radial-tangential only).

    An image size given in the file must be the images'. CalibrationError naming the file and
    field otherwise."""
    fs = open_yaml(path)
    root = fs.root()
    try:
        own = _size(root, path)
        if own is not None and own != tuple(size):
            raise CalibrationError(f"{path}: image size {own[0]}x{own[1]} differs from the "
                                   f"images' {size[0]}x{size[1]}")
        left, right = fs.getNode("left"), fs.getNode("right")
        if left.isMap() or right.isMap():
            cams = []
            for side, node in (("left", left), ("right", right)):
                if not node.isMap():
                    raise CalibrationError(f"{path}: missing map '{side}' (the per-camera form "
                                           "needs 'left' and 'right')")
                cams.append(_camera(node, side, path, size))
            rig = RectifiedRig.from_rectification(*cams, source=str(path))
        else:
            k1, k1n = field_node(root, ("K1", "M1"))
            if k1 is None or field_node(root, ("T",))[0] is None:
                raise CalibrationError(
                    f"{path}: neither form of calibration: give maps 'left' and 'right' (K, D, "
                    "R, P each) or the stereo extrinsic K1, D1, K2, D2, R, T")
            model = text(field_node(root, ("distortion_model",))[0])
            if model not in ("", "plumb_bob", "radial-tangential", "rational_polynomial"):
                raise CalibrationError(f"{path}: field 'distortion_model': {model!r} is not "
                                       "supported with R, T (radial-tangential models only)")
            k = [_matrix(root, names, (3, 3), path) for names in (("K1", "M1"), ("K2", "M2"))]
            d = [numbers(field_node(root, (n,))[0], n, None, path, counts=(0, 4, 5, 8, 12, 14))
                 if field_node(root, (n,))[0] is not None else np.zeros(5) for n in ("D1", "D2")]
            r = _matrix(root, ("R",), (3, 3), path)
            t = numbers(field_node(root, ("T",))[0], "T", 3, path)
            if not np.allclose(r @ r.T, np.eye(3), atol=1e-5) or np.linalg.det(r) < 0:
                raise CalibrationError(f"{path}: field 'R' is not a rotation (R R^T != I or "
                                       "det < 0)")
            rig = RectifiedRig.from_raw(k[0], d[0], k[1], d[1], r, t, size, str(path))
    finally:
        fs.release()
    if rig.baseline > MAX_BASELINE:
        warnings.warn(f"{path}: baseline {rig.baseline:.1f} m; the calibration's lengths must "
                      "be metres (are T or P in millimetres?)", stacklevel=2)
    return rig


def read_stereo_calib(root: Path, size: tuple[int, int]) -> RectifiedRig:
    """The rig of ``root/calib.yaml`` (:func:`read_calib_yaml`) or ``root/calib.txt`` (KITTI
    ``P0``/``P1``); one of them, not both."""
    yaml_file, txt_file = root / "calib.yaml", root / "calib.txt"
    if yaml_file.is_file() and txt_file.is_file():
        raise DatasetError(f"{root}: holds both calib.yaml and calib.txt; keep the one to use")
    if yaml_file.is_file():
        return read_calib_yaml(yaml_file, size)
    if txt_file.is_file():
        return read_kitti_calib(txt_file, size)
    raise CalibrationError(f"{yaml_file}: calibration file is missing (or calib.txt with "
                           "KITTI's P0:, P1:)")


def read_tum_poses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Times [N] and planar poses [N, 3] (x, y, yaw of the robot's x axis) of a TUM file
    (``time x y z qx qy qz qw``); DatasetError naming the file and line of a bad row, a zero
    quaternion or a time not after the one before."""
    table = read_table(path, 8)
    data = table.data
    norm = np.linalg.norm(data[:, 4:8], axis=1)
    if not np.all(norm > 1e-9):
        line = table.lines[int(np.flatnonzero(~(norm > 1e-9))[0])]
        raise DatasetError(f"{path}:{line}: quaternion of zero length")
    i = first_not_increasing(data[:, 0])
    if i is not None:
        raise DatasetError(f"{path}:{table.lines[i]}: time {data[i, 0]} is not after "
                           f"{data[i - 1, 0]} (rows must be in time order)")
    r = Rotation.from_quat(data[:, 4:8] / norm[:, None]).as_matrix()
    return data[:, 0], np.column_stack([data[:, 1], data[:, 2],
                                        np.arctan2(r[:, 1, 0], r[:, 0, 0])])


TIME_TOLERANCE = 1e-6  # seconds: a frame this near a row takes that row's pose


def poses_at(times: np.ndarray, poses: np.ndarray, at: np.ndarray,
             max_gap: float) -> np.ndarray:
    """Planar ``poses`` [N, 3] at ``times`` [N] read at the times ``at`` [T]: a row's own pose
    within ``TIME_TOLERANCE`` of its time, else linear between the rows around (yaw along the
    shorter turn); NaN outside the rows' span or where the rows around are more than
    ``max_gap`` seconds apart."""
    times, poses, at = (np.asarray(a, np.float64) for a in (times, poses, at))
    out = np.full((len(at), 3), np.nan)
    last = len(times) - 1
    right = np.clip(np.searchsorted(times, at), 0, last)
    left = np.clip(right - 1, 0, last)
    near = np.where(np.abs(times[left] - at) < np.abs(times[right] - at), left, right)
    exact = np.abs(times[near] - at) <= TIME_TOLERANCE
    span = times[right] - times[left]
    between = ~exact & (at > times[0]) & (at < times[-1]) & (span <= max_gap)
    frac = np.where(between, (at - times[left]) / np.where(span > 0, span, 1.0), 0.0)[:, None]
    turn = np.angle(np.exp(1j * (poses[right, 2] - poses[left, 2])))
    mid = poses[left] + frac * np.column_stack([poses[right, :2] - poses[left, :2], turn])
    mid[:, 2] = np.angle(np.exp(1j * mid[:, 2]))
    out[between] = mid[between]
    out[exact] = poses[near[exact]]
    return out


def _frame_times(root: Path, n: int, period: float) -> tuple[np.ndarray, str]:
    """Seconds of each of the ``n`` pairs and where they come from."""
    path = root / "times.txt"
    if not path.is_file():
        return np.arange(n) * period, f"{period} s apart (no times.txt)"
    table = read_table(path, 1)
    if len(table.data) != n:
        raise DatasetError(f"{path}: {len(table.data)} times for {n} image pairs (one line a "
                           "pair, in the order of the file names)")
    times = table.data[:, 0]
    i = first_not_increasing(times)
    if i is not None:
        raise DatasetError(f"{path}:{table.lines[i]}: time {times[i]} of pair {i} is not after "
                           f"{times[i - 1]} (times must increase)")
    return times, str(path)


def _tum_at(path: Path, times: np.ndarray, clock: str, max_gap: float) -> np.ndarray | None:
    """A TUM file's planar poses at the frames' ``times`` (None when there is no file);
    DatasetError when its rows cover none of them."""
    if not path.is_file():
        return None
    stamps, poses = read_tum_poses(path)
    out = poses_at(stamps, poses, times, max_gap)
    if not np.isfinite(out[:, 0]).any():
        raise DatasetError(f"{path}: its times ({stamps[0]} to {stamps[-1]} s) cover none of the "
                           f"frames ({times[0]} to {times[-1]} s, {clock}): the times must be on "
                           "the clock of times.txt")
    return out


def stereo_frontend(root: str | Path, params: StereoParams, *,
                    progress: Callable[[int, int], None] | None = None) -> FrontEndResult:
    """Run the stereo front-end over a stereo folder (see the module docstring for the layout);
    ``progress(done, total)`` follows the frames."""
    root = Path(root)
    pairs = find_pairs(root)
    if params.max_frames is not None and params.max_frames < 1:
        raise DatasetError(f"max_frames must be at least 1, got {params.max_frames}")
    times, clock = _frame_times(root, len(pairs), params.frame_period)
    if params.max_frames is not None:
        pairs, times = pairs[:params.max_frames], times[:params.max_frames]
    first = read_image(pairs[0][0])
    rig = read_stereo_calib(root, (first.shape[1], first.shape[0]))
    t_robot_cam = np.asarray(params.mount, np.float64) @ make_transform(rig.r_left.T,
                                                                         np.zeros(3))
    gt = _tum_at(root / "groundtruth.txt", times, clock, params.max_gap)
    odo = _tum_at(root / "odometry.txt", times, clock, params.max_gap)
    wheel = None if odo is None else increments_2d(odo)
    known = None if gt is None else np.flatnonzero(np.isfinite(gt[:, 0]))
    origin = None if times[0] == 0 else int(round(float(times[0]) * 1e9))

    def load(t: int) -> tuple[np.ndarray, np.ndarray]:
        return read_image(pairs[t][0]), read_image(pairs[t][1])

    return run_frontend(load, len(pairs), rig, t_robot_cam, times - times[0], params.frontend,
                        aids=SensorAids(wheel=wheel), ground_truth=gt,
                        initial_pose=None if gt is None else gt[known[0]], source=str(root),
                        progress=progress, time_origin_ns=origin)


def _load(src: Source, config: Config, progress: Callable[[int, int], None] | None = None
          ) -> LoadedSource:
    mount = camera_mount(config, None, f"--source stereo {src.path}")
    default = StereoParams(mount=mount).frontend
    params = StereoParams(mount=mount, max_frames=src.max_frames, frontend=FrontEndParams(
        local_map=localmap_params(config, "stereo"), on_bad_frame=src.on_bad_frame,
        stereo=stereo_settings(config, default.stereo)))
    result = stereo_frontend(src.path, params, progress=progress)
    print(result.summary.text())
    return LoadedSource(result.run, f"stereo folder {src.path}")


SOURCE = DataSource(name="stereo", help="a folder of stereo pairs (left/, right/) with "
                    "calib.yaml or calib.txt; the mount from [rig]", load=_load, images=True,
                    path="the stereo folder, holding left/, right/ and calib.yaml")
