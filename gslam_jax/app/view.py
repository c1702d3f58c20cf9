"""``gslam view RESULTS_DIR`` and ``gslam run --viewer``: runs shown in the Rerun viewer.

``gslam view`` reads a finished results folder (:func:`read_results`: map.npz, the TUM paths,
trace.npz; or a ``gslam merge`` folder: the merged map and each run's path in its frame) and
logs it (``app.viewer``): the paths and the map as they ended, the per-frame best and mean
poses and ESS on the timelines. ``gslam run --viewer`` / ``--viewer-save`` log the run as it
goes (:class:`RunWatch`: ``slam.run_slam``'s ``on_chunk``, every ``--viewer-every`` frames)
and, once the results are written, the reported path and the final map from the results
folder. The particle clouds exist only while the filter runs: ``gslam view`` has none.

A recording file (``--save``, ``--viewer-save``) is written beside its name and renamed onto
it once complete (``outfile.staged_file``): a failed or terminated command leaves none, and an
existing one is replaced only with ``--overwrite``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import re
import sys
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np

from gslam_jax.app.arguments import add_deprecated, add_shared, spelled
from gslam_jax.app.outfile import staged_file
from gslam_jax.app.viewer import RunViewer, ViewerError, check_viewer, open_viewer

__all__ = ["add_parser", "add_run_arguments", "cmd_view", "ResultsRecord", "read_results",
           "log_results", "RunWatch", "VIEWER_EVERY"]

VIEWER_EVERY = 50  # frames between the live viewer's path and map updates (filter chunks)


class ResultsRecord(NamedTuple):
    """What ``gslam view`` shows of a results folder (NumPy, the map frame)."""

    name: str
    times: np.ndarray                  # [T] seconds from the first frame (merge: [0])
    reported: np.ndarray | None        # [T, 3] trajectory_tum.txt ([filter] estimate; merge:
                                       # None)
    vo: np.ndarray | None              # [T, 3] vo_tum.txt
    ground_truth: np.ndarray | None    # [T, 3] ground_truth_tum.txt on the frames' times (NaN
                                       # where unknown)
    best_pose: np.ndarray | None       # [T, 3] trace.npz
    mean_pose: np.ndarray | None       # [T, 3] trace.npz
    ess: np.ndarray | None             # [T] trace.npz
    std: np.ndarray                    # [nx, ny] the map's expected std (NaN: unobserved)
    origin: tuple[float, float]        # on the lattice's axes (``GridMap``)
    resolution: float
    heading: float = 0.0               # the lattice's axes in the map frame (``GridMap``)
    runs: tuple = ()                   # merge: (entity name, [n, 3] path) of each run placed


def _tum(path: Path) -> tuple[np.ndarray, np.ndarray]:
    from gslam_jax.gridmap import MapFileError
    from gslam_jax.io import read_tum

    try:
        return read_tum(path)
    except (ValueError, IndexError) as err:
        raise MapFileError(f"{path}: not a TUM trajectory ({err})") from err


def read_results(folder: str | Path) -> ResultsRecord:
    """The results folder of a ``gslam run``: map.npz and trajectory_tum.txt (required),
    vo_tum.txt, ground_truth_tum.txt and trace.npz (when present). A MapFileError names a
    missing or unreadable file; the truth is placed on the frames by its times."""
    from gslam_jax.gridmap import MapFileError, load_map

    folder = Path(folder)
    if not folder.is_dir():
        raise MapFileError(f"{folder}: not a folder; give a gslam run results folder")
    grid = load_map(folder)
    merged = _merged_runs(folder)
    if merged is not None:
        return ResultsRecord(folder.name, np.zeros(1), None, None, None, None, None, None,
                             grid.expected_std(), tuple(grid.origin), float(grid.resolution),
                             float(grid.heading), merged)
    tum = folder / "trajectory_tum.txt"
    if not tum.is_file():
        raise MapFileError(f"{folder} has no trajectory_tum.txt: give a gslam run results "
                           "folder")
    stamps, reported = _tum(tum)
    T = len(stamps)
    vo = gt = best = mean = ess = None
    if (folder / "vo_tum.txt").is_file():
        vo = _tum(folder / "vo_tum.txt")[1]
        if len(vo) != T:
            raise MapFileError(f"{folder / 'vo_tum.txt'}: {len(vo)} poses, trajectory_tum.txt "
                               f"has {T}")
    if (folder / "ground_truth_tum.txt").is_file():
        gt_t, gt_p = _tum(folder / "ground_truth_tum.txt")
        gt = np.full((T, 3), np.nan)
        at = np.searchsorted(stamps, gt_t)
        ok = (at < T) & (np.abs(stamps[np.minimum(at, T - 1)] - gt_t) < 1e-6)
        gt[at[ok]] = gt_p[ok]
    trace = folder / "trace.npz"
    if trace.is_file():
        try:
            with np.load(trace, allow_pickle=False) as data:
                fields = {k: np.asarray(data[k]) for k in ("best_pose", "mean_pose", "ess")
                          if k in data.files}
        except Exception as err:  # zip or format errors: an unreadable file
            raise MapFileError(f"{trace}: not a readable .npz archive ({err})") from err
        for key, value in fields.items():
            if len(value) != T:
                raise MapFileError(f"{trace}: field '{key}' has {len(value)} frames, "
                                   f"trajectory_tum.txt has {T}")
        best, mean, ess = (fields.get(k) for k in ("best_pose", "mean_pose", "ess"))
    return ResultsRecord(folder.name, stamps - stamps[0], reported, vo, gt, best, mean, ess,
                         grid.expected_std(), tuple(grid.origin), float(grid.resolution),
                         float(grid.heading))


def _merged_runs(folder: Path) -> tuple | None:
    """The runs of a ``gslam merge`` folder (summary.json's ``runs``, each path from its
    trajectory file in the merged frame), or None for a folder gslam merge did not write."""
    from gslam_jax.gridmap import MapFileError

    if (folder / "trajectory_tum.txt").is_file():
        return None
    try:
        entries = json.loads((folder / "summary.json").read_text()).get("runs")
    except (OSError, ValueError, AttributeError):
        return None
    if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
        return None
    runs = []
    for i, entry in enumerate(entries):
        name = re.sub(r"[^A-Za-z0-9_-]+", "_", str(entry.get("name", i)))
        file = entry.get("trajectory")
        if file is None:  # a run given as a bare map.npz has no path
            continue
        if not isinstance(file, str) or "/" in file or not (folder / file).is_file():
            raise MapFileError(f"{folder / 'summary.json'}: run {i} names trajectory {file!r}, "
                               "which is not in the folder")
        runs.append((f"run{i}_{name}", _tum(folder / file)[1]))
    return tuple(runs)


def log_results(viewer: RunViewer, record: ResultsRecord, live: bool = False) -> None:
    """Log a finished run: the per-frame poses and ESS (unless ``live``: the run logged them),
    the paths and the map. Static for ``gslam view``; after a live run at its last frame."""
    last = len(record.times) - 1
    frame, time_s = (last, float(record.times[last])) if live else (None, None)
    if not live and record.best_pose is not None and record.mean_pose is not None:
        viewer.frames(0, record.times, record.best_pose, record.mean_pose, record.ess)
    paths = {} if record.reported is None else {"reported": record.reported}
    paths.update(record.runs)
    if not live:
        paths.update({k: v for k, v in (("vo", record.vo), ("ground_truth", record.ground_truth))
                      if v is not None})
    if paths:
        viewer.paths(paths, frame, time_s)
    viewer.map(record.std, record.origin, record.resolution, frame, time_s, record.heading)


class RunWatch:
    """The viewer of ``gslam run --viewer / --viewer-save``, or nothing without them: a
    context manager with ``on_chunk`` and ``chunk`` for ``pipeline.run_pipeline``, then
    :meth:`finish` with the results folder."""

    def __init__(self, viewer: RunViewer | None = None, every: int = VIEWER_EVERY,
                 staged: contextlib.ExitStack | None = None):
        self.viewer = viewer
        self.staged = staged  # the recording's staged_file, renamed into place on success
        self.on_chunk: Callable | None = None if viewer is None else viewer.chunk
        self.chunk: int | None = None if viewer is None else every

    @classmethod
    def open(cls, spawn: bool, save: Path | None, every: int | None = None,
             name: str = "gslam run", overwrite: bool = False) -> RunWatch:
        """Checked before any work (``viewer.check_viewer``: an existing ``save`` only with
        ``overwrite``), then opened; a RunWatch that does nothing without ``spawn`` or
        ``save``. The recording is written to a temporary file beside ``save``, renamed onto
        it when the watch is left without an error, removed otherwise."""
        if not spawn and save is None:
            if every is not None:
                raise ViewerError("--viewer-every sets the live viewer's updates: give "
                                  "--viewer or --viewer-save too")
            return cls()
        check_viewer(spawn, save, overwrite=overwrite)
        staged = contextlib.ExitStack()
        tmp = None if save is None else staged.enter_context(staged_file(save, "--viewer-save"))
        try:
            viewer = open_viewer(name, spawn, tmp)
        except BaseException:
            staged.__exit__(*sys.exc_info())  # the temporary removed
            raise
        return cls(viewer, every or VIEWER_EVERY, staged)

    def finish(self, folder: Path) -> None:
        """The results folder's reported path and map at the last frame, then close."""
        if self.viewer is not None:
            log_results(self.viewer, read_results(folder), live=True)
        self.close()

    def close(self) -> None:
        """Flush and close the recording (what was logged stays); idempotent."""
        if self.viewer is not None:
            self.viewer.close()
            self.viewer = None

    def __enter__(self) -> RunWatch:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
        if self.staged is not None:  # renamed into place, or removed after an error
            staged, self.staged = self.staged, None
            staged.__exit__(*exc)


def add_run_arguments(p: argparse.ArgumentParser, positive_int) -> None:
    """``gslam run``'s viewer options."""
    p.add_argument("--viewer", action="store_true", help="show the run in the Rerun viewer as "
                   "it goes (particles, best and mean paths, VO path, ground truth, map); needs "
                   "a display and the extra 'viewer' (pip install 'gslam-jax[viewer]')")
    add_shared(p, "--viewer-save")
    p.add_argument("--viewer-every", type=positive_int, metavar="N", help="frames between the "
                   f"viewer's path and map updates (default {VIEWER_EVERY}; the filter runs in "
                   "chunks of N frames, with the same results)")


def add_parser(sub) -> None:
    p = sub.add_parser("view", help="show a finished run's (or merge's) results folder in "
                       "the Rerun viewer")
    p.add_argument("results", type=Path, metavar="RESULTS_DIR",
                   help="a gslam run or gslam merge results folder")
    add_shared(p, "--viewer-save", "--overwrite")  # instead of spawning the viewer
    add_deprecated(p, "--save", "use --viewer-save FILE.rrd, as gslam run does",
                   dest="viewer_save", type=Path, metavar="FILE.rrd")
    p.set_defaults(func=cmd_view)


def cmd_view(args: argparse.Namespace) -> int:
    spawn = args.viewer_save is None
    option = spelled(args, "viewer_save", "--viewer-save")
    check_viewer(spawn, args.viewer_save, spawn_option="gslam view", save_option=option,
                 overwrite=args.overwrite)
    record = read_results(args.results)
    # summary.json names the run's source, when it is there
    source = ""
    try:
        source = json.loads((args.results / "summary.json").read_text()).get("source", "")
    except (OSError, ValueError, AttributeError):
        pass  # no summary (or not one gslam wrote): the folder's name alone
    with contextlib.ExitStack() as staged:
        tmp = None if spawn else staged.enter_context(staged_file(args.viewer_save, option))
        viewer = open_viewer(f"{record.name}" + (f": {source}" if source else ""), spawn, tmp)
        log_results(viewer, record)
        viewer.close()
    what = f"{len(record.runs)} runs merged" if record.reported is None else \
        f"{len(record.times)} frames"
    print(f"{'recording: ' + str(args.viewer_save) if args.viewer_save else 'sent to the viewer'}: "
          f"{what} of {args.results}")
    return 0
