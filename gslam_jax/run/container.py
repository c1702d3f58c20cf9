"""The Run: everything the filter consumes, stacked as arrays before the jitted scan starts.

A Run is produced by a source (simulator, dataset adapter, native ``.npz`` log) after the
front-end (VO, local-map builder) has processed every frame, so the whole sequence is known when
the filter is compiled. The native file format is exactly the fields below (docs/formats.md).
"""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import BinaryIO, NamedTuple

import numpy as np

from gslam_jax.errors import RunError
from gslam_jax.run.checks import (HEADING_LIMIT, check_controls, check_start_pose,
                                  check_statistics, check_types, describe_cells,
                                  normalise_stored)

__all__ = ["Run", "RunError", "integrate_controls", "known_positions", "load_run", "save_run",
           "validate_run"]


class Run(NamedTuple):
    """A whole log, ready for the filter.

    Attributes:
        controls: [T, 3] VO increments u_t = (dx, dy, dtheta) in the robot frame at t-1
            (metres, radians); ``controls[0]`` moves from the initial pose to frame 0.
        obs_index: [T] int; index into ``local_maps`` of the local map completed at frame t,
            or -1 where frame t carries no local map (prediction only).
        local_maps: [M, L, L, 3] per-cell sufficient statistics (n, sum z, sum z^2) of a
            robot-centred grid at frame ``obs_index == m``; cell (i, j) covers robot-frame
            x in [(i - L/2) res, (i - L/2 + 1) res), y likewise with j. n is a whole number
            and n sum z^2 >= (sum z)^2 (up to the rounding of the dtype a file stores them
            in: float32 statistics may round by about n eps32 relative).
        resolution: local-map cell side in metres, a scalar (must equal the filter's map
            resolution; a file may store it as a size-1 array).
        timestamps: [T] seconds, finite and strictly increasing.
        ground_truth: [T, 3] true poses (x, y, theta) or None; NaN rows mark frames without
            ground truth (the metrics skip them).
        vo_failed: [T] bool, frames whose control came from the wheel/IMU fallback (a file
            may store it as integers 0/1); the filter weighs their motion with ``[motion]
            fallback_scale`` times the noise (``sizing.fallback_frames``).
        initial_pose: [3] pose before frame 0 (ground-truth frame; zeros if unknown).
        time_origin_ns: the dataset's own clock at timestamp 0, integer nanoseconds (EuRoC:
            its first frame's stamp), or None (the timestamps are the dataset's clock). The
            TUM outputs add it back; the filter and GPS use ``timestamps``.
        sensor: how the local maps were made, one of ``choices.SENSORS`` ("stereo": the
            stereo front-end; "points": the simulator's point sensor), or None (unknown,
            treated as "points"). It picks the automatic ``[filter] ess_target``.
        lattice_headings: [M] radians, or None (all 0): the angle of each local map's lattice
            against the robot frame at its frame. Local map m's cell (i, j) then covers the
            square above, turned by ``lattice_headings[m]`` about the robot: a cell centre c of
            the lattice lies at R(lattice_headings[m]) c in the robot frame. 0: the robot's
            own axes (the paper's local maps); ``[localmap] lattice = "map"`` turns each
            lattice onto the map's axes at the VO pose (``localmap.LocalMapBuilder``).
    """

    controls: np.ndarray
    obs_index: np.ndarray
    local_maps: np.ndarray
    resolution: float
    timestamps: np.ndarray
    ground_truth: np.ndarray | None = None
    vo_failed: np.ndarray | None = None
    initial_pose: np.ndarray | None = None
    time_origin_ns: int | None = None
    sensor: str | None = None
    lattice_headings: np.ndarray | None = None

    @property
    def num_frames(self) -> int:
        return int(self.controls.shape[0])

    @property
    def num_local_maps(self) -> int:
        return int(self.local_maps.shape[0])

    @property
    def has_obs(self) -> np.ndarray:
        return self.obs_index >= 0

    def start_pose(self) -> np.ndarray:
        if self.initial_pose is None:
            return np.zeros(3)
        return np.asarray(self.initial_pose, dtype=np.float64)

    def lattice_heading_array(self) -> np.ndarray:
        """[max(M, 1)] float32: ``lattice_headings``, zeros where None (the filter's input)."""
        if self.lattice_headings is None:
            return np.zeros(max(self.num_local_maps, 1), np.float32)
        h = np.asarray(self.lattice_headings, np.float32)
        return h if h.size else np.zeros(1, np.float32)

    def vo_poses(self) -> np.ndarray:
        """[T, 3] poses from integrating the VO controls alone (the VO-only trajectory)."""
        return integrate_controls(self.controls, self.start_pose())

    def distance(self) -> float:
        """Distance travelled according to the controls, metres."""
        return float(np.sum(np.hypot(self.controls[:, 0], self.controls[:, 1])))


def integrate_controls(controls: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
    """Compose robot-frame increments into world poses (noise-free eq. 1), float64."""
    controls = np.asarray(controls, dtype=np.float64)
    pose = np.zeros(3) if start is None else np.array(start, dtype=np.float64)
    out = np.empty_like(controls)
    for t, (dx, dy, dth) in enumerate(controls):
        c, s = np.cos(pose[2]), np.sin(pose[2])
        pose = np.array([pose[0] + c * dx - s * dy, pose[1] + s * dx + c * dy, pose[2] + dth])
        out[t] = pose
    return out


def validate_run(run: Run, source: str = "<run>", stats_dtype: np.dtype | None = None) -> Run:
    """Check shapes, types and values; raise RunError naming the field and frame.

    Required: finite controls; finite, strictly increasing timestamps; integer point counts
    n >= 0 with n sum z^2 >= (sum z)^2 (a variance >= 0, up to the rounding of the dtype the
    statistics were accumulated in: ``stats_dtype``, default ``local_maps``' own); a finite
    initial pose. ``ground_truth`` may hold NaN rows: frames without ground truth (the metrics
    skip them). The start pose within reach of float32 (``check_start_pose``); no control
    turning more than pi or moving faster than MAX_SPEED in one frame (``check_controls``).
    """

    def fail(field: str, msg: str) -> None:
        raise RunError(f"{source}: field '{field}': {msg}")

    if not isinstance(run, Run):
        raise RunError(f"{source}: expected a gslam_jax.Run, got {type(run).__name__}")
    check_types(run._asdict(), fail)
    controls = np.asarray(run.controls)
    if controls.ndim != 2 or controls.shape[1] != 3:
        fail("controls", f"expected shape [T, 3], got {controls.shape}")
    T = controls.shape[0]
    if T == 0:
        fail("controls", "the run has no frames")
    bad = ~np.isfinite(controls).all(axis=1)
    if bad.any():
        fail("controls", f"non-finite value (NaN or inf) at frame {int(np.argmax(bad))}"
             f" ({int(bad.sum())} frames in all)")
    obs_index = np.asarray(run.obs_index)
    if obs_index.shape != (T,):
        fail("obs_index", f"expected shape [{T}], got {obs_index.shape}")
    if not np.issubdtype(obs_index.dtype, np.integer):
        fail("obs_index", f"expected integers, got {obs_index.dtype}")
    maps = np.asarray(run.local_maps)
    if maps.ndim != 4 or maps.shape[3] != 3 or maps.shape[1] != maps.shape[2]:
        fail("local_maps", f"expected shape [M, L, L, 3], got {maps.shape}")
    M = maps.shape[0]
    used = obs_index[obs_index >= 0]
    if (obs_index < -1).any():
        fail("obs_index", f"value below -1 at frame {int(np.argmax(obs_index < -1))}")
    if used.size and used.max() >= M:
        frame = int(np.argmax(obs_index >= M))
        fail("obs_index",
             f"frame {frame} refers to local map {obs_index[frame]} but only {M} exist")

    def first_map(bad_cells: np.ndarray) -> str:
        return describe_cells(bad_cells, obs_index)

    check_statistics(maps, maps.dtype if stats_dtype is None else stats_dtype,
                     lambda message: fail("local_maps", message), first_map)
    resolution = float(run.resolution)
    if not (np.isfinite(resolution) and resolution > 0):
        fail("resolution", f"must be a positive number of metres, got {run.resolution}")
    ts = np.asarray(run.timestamps)
    if ts.shape != (T,):
        fail("timestamps", f"expected shape [{T}], got {ts.shape}")
    if not np.isfinite(ts).all():
        fail("timestamps", f"non-finite value (NaN or inf) at frame "
             f"{int(np.argmax(~np.isfinite(ts)))}")
    if (np.diff(ts) <= 0).any():
        t = int(np.argmax(np.diff(ts) <= 0)) + 1
        fail("timestamps", f"not increasing at frame {t} ({float(ts[t - 1])!r} s, "
             f"then {float(ts[t])!r} s)")
    if run.ground_truth is not None and np.asarray(run.ground_truth).shape != (T, 3):
        fail("ground_truth", f"expected shape [{T}, 3], got {np.asarray(run.ground_truth).shape}")
    if run.vo_failed is not None and np.asarray(run.vo_failed).shape != (T,):
        fail("vo_failed", f"expected shape [{T}], got {np.asarray(run.vo_failed).shape}")
    if run.initial_pose is not None:
        pose = np.asarray(run.initial_pose)
        if pose.shape != (3,):
            fail("initial_pose", f"expected shape [3], got {pose.shape}")
        if not np.isfinite(pose).all():
            fail("initial_pose", f"non-finite value (NaN or inf): {pose.tolist()}")
        check_start_pose(pose.astype(np.float64), resolution, fail)
    if run.lattice_headings is not None:
        h = np.asarray(run.lattice_headings)
        M = int(np.asarray(run.local_maps).shape[0])
        if h.shape != (M,):
            fail("lattice_headings", f"expected shape [{M}] (one per local map), got {h.shape}")
        if not np.isfinite(h).all():
            fail("lattice_headings", f"non-finite value (NaN or inf) at local map "
                 f"{int(np.argmax(~np.isfinite(h)))}")
        if (np.abs(h) > HEADING_LIMIT).any():
            m = int(np.argmax(np.abs(h) > HEADING_LIMIT))
            fail("lattice_headings", f"local map {m}: {float(h[m]):.6g} rad is beyond "
                 f"{HEADING_LIMIT:g} rad (radians expected)")
    check_controls(controls.astype(np.float64), ts.astype(np.float64), fail)
    return run


_REQUIRED = ("controls", "obs_index", "local_maps", "resolution", "timestamps")
_OPTIONAL = ("ground_truth", "vo_failed", "initial_pose", "time_origin_ns", "sensor",
             "lattice_headings")


def save_run(path: str | Path | BinaryIO, run: Run) -> None:
    """Write a Run as a native ``.npz`` file (the format of docs/formats.md); ``path`` may
    be an open binary file."""
    validate_run(run, str(getattr(path, "name", path)))
    arrays = {name: np.asarray(getattr(run, name)) for name in _REQUIRED}
    for name in _OPTIONAL:
        value = getattr(run, name)
        if value is not None:
            arrays[name] = np.asarray(value, np.int64) if name == "time_origin_ns" else \
                np.asarray(value)
    np.savez_compressed(path, **arrays)


def known_positions(ground_truth: np.ndarray) -> np.ndarray:
    """[T] bool: frames whose ground-truth position (x, y) is finite (NaN rows, or a NaN x or
    y, mark frames without ground truth; a NaN heading alone does not)."""
    return np.isfinite(np.asarray(ground_truth, np.float64)[:, :2]).all(axis=1)


def load_run(path: str | Path) -> Run:
    """Read and validate a native ``.npz`` Run file."""
    path = Path(path)
    if not path.exists():
        raise RunError(f"{path}: no such file")
    if not zipfile.is_zipfile(path):  # np.load would try it as .npy, then as a pickle
        raise RunError(f"{path}: not a .npz archive (not a zip file)")
    try:
        data = np.load(path, allow_pickle=False)
    except Exception as err:  # numpy raises several types for corrupt archives
        raise RunError(f"{path}: not a readable .npz archive ({err})") from err
    with data:
        missing = [k for k in _REQUIRED if k not in data.files]
        if missing:
            raise RunError(f"{path}: missing field(s) {', '.join(missing)}")
        unknown = sorted(set(data.files) - set(_REQUIRED) - set(_OPTIONAL))
        if unknown:
            raise RunError(f"{path}: unknown field(s) {', '.join(unknown)}")
        fields = {}
        for k in data.files:
            try:
                fields[k] = data[k]
            except ValueError as err:  # object arrays (e.g. a None saved by np.savez)
                raise RunError(f"{path}: field '{k}': not an array of numbers ({err})") from err

    def fail(field: str, msg: str) -> None:
        raise RunError(f"{path}: field '{field}': {msg}")

    fields = normalise_stored(fields, fail)
    check_types(fields, fail)  # before the conversions below, which would raise or hide it
    stats_dtype = fields["local_maps"].dtype  # the rounding of the statistics is that dtype's
    run = Run(
        controls=fields["controls"].astype(np.float64),
        obs_index=fields["obs_index"],
        local_maps=fields["local_maps"].astype(np.float64),
        resolution=float(fields["resolution"]),
        timestamps=fields["timestamps"].astype(np.float64),
        ground_truth=fields.get("ground_truth"),
        vo_failed=fields.get("vo_failed"),
        initial_pose=fields.get("initial_pose"),
        time_origin_ns=(int(fields["time_origin_ns"]) if "time_origin_ns" in fields else None),
        sensor=str(fields["sensor"]) if "sensor" in fields else None,
        lattice_headings=(fields["lattice_headings"].astype(np.float64)
                          if "lattice_headings" in fields else None),
    )
    return validate_run(run, str(path), stats_dtype=stats_dtype)
