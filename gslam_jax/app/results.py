"""A results folder that is written completely or not at all.

A command writes into a staging folder beside the target (``.<name>.partial-<random>``),
created before any work, so that a place where nothing can be written is reported before the
run, not after it. When every output is written, a marker ``COMPLETE`` (JSON: the command,
the finishing time, every file with its size) is added and the folder is renamed into place in
one step. A ``--out`` that is a symbolic link is followed: the results go to the folder it
points to (present or not), beside which they are staged. A failed or interrupted command
removes its staging folder, and so does one ended by SIGTERM (like Ctrl-C; it exits 143:
``termination``); one
killed outright (SIGKILL) leaves it hidden beside the target, never a half-written target.

An existing, non-empty target is refused unless ``overwrite``; then it is replaced as a whole
(the old run's files are never mixed with the new run's), and only when it holds gslam
results, never an unrelated folder: only the files listed by a marker gslam wrote (its
``format`` header, the files present), or, unmarked, only names gslam writes. A file named
COMPLETE that gslam did not write makes the folder the user's.
"""

from __future__ import annotations

import contextlib
import datetime
import errno
import json
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Iterator, NamedTuple

from gslam_jax.app.termination import sigterm_as_exit
from gslam_jax.errors import InputError

__all__ = ["MARKER", "MARKER_FORMAT", "RESULT_FILES", "ResultsError", "Staged", "results_folder",
           "is_complete", "writing"]

MARKER = "COMPLETE"

# Every name a gslam command writes into a results folder (run, search, tune, compare): an
# unmarked folder holding only these (from a version without the marker) may be overwritten.
RESULT_FILES = frozenset({
    MARKER, "summary.json", "config.toml", "simulation.json", "trajectory_tum.txt",
    "trajectory_kitti.txt", "trajectory_robot_kitti.txt", "vo_tum.txt", "map_path_tum.txt",
    "ground_truth_tum.txt",
    "map.npz", "map.png", "map_occupancy.pgm", "map_occupancy.yaml",
    "maps_vo_vs_slam.png", "ground_truth.png", "errors.png", "ess.png", "trace.npz",
    "trajectory_utm.txt",
    "map_utm.png", "map_utm.tif", "map_utm_north.tif", "map_utm_figure.png",
    "map_utm.pgw", "gps_alignment.npz", "results.csv", "results.json", "best.toml",
    "tuned.json", "tuned.toml", "compare.json", "compare_fig4.png", "bench.json", "bench.png",
    "table1.json"})


class ResultsError(InputError):
    """The results folder cannot be used or written: the message names it and says why."""


class Staged(NamedTuple):
    """A command's results folder while it is written: ``staging`` (write here), the
    ``target`` it becomes when complete, and ``name`` for messages (e.g. "--out DIR")."""

    staging: Path
    target: Path
    name: str


class _Taken(ResultsError):
    """``out`` was taken by another command while this one ran; the results stay staged."""


# The first key of every marker gslam writes; a COMPLETE file without it is not gslam's.
MARKER_FORMAT = "gslam results"


def _marker_files(folder: Path) -> set[str] | None:
    """The files listed by ``folder``'s marker when gslam wrote it (JSON with the ``format``
    header, or from earlier versions a ``gslam ...`` command; the finishing time; the files,
    each present), else None: a user's file named COMPLETE does not count."""
    try:
        marker = json.loads((folder / MARKER).read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    if not isinstance(marker, dict):
        return None
    command, files = marker.get("command"), marker.get("files")
    ours = marker.get("format") == MARKER_FORMAT or \
        (isinstance(command, str) and command.startswith("gslam "))
    if not (ours and isinstance(marker.get("finished"), str) and isinstance(files, dict)):
        return None
    names = set(files)
    if not all(isinstance(n, str) and "/" not in n and (folder / n).is_file() for n in names):
        return None
    return names


def is_complete(folder: str | Path) -> bool:
    """True when ``folder`` holds the completeness marker of a finished gslam command."""
    return _marker_files(Path(folder)) is not None


def _follow_link(target: Path, name: str) -> tuple[Path, str]:
    """``target`` with a symbolic link resolved: the results are written into (and renamed onto)
    the folder it points to, present or not, never onto the link itself. ResultsError for a
    link that resolves to no place (a loop)."""
    if not target.is_symlink():
        return target, name
    resolved = Path(os.path.realpath(target))
    if resolved.is_symlink():  # realpath stops at a loop
        raise ResultsError(f"{name}: is a symbolic link that resolves to no folder (a loop); "
                           "nothing was run")
    return resolved, f"{name} (a link to {resolved})"


def _check_target(target: Path, name: str, overwrite: bool) -> None:
    """ResultsError when ``target`` may not receive the results (before any work)."""
    if not target.exists():
        return
    if not target.is_dir():
        raise ResultsError(f"{name}: exists and is not a directory")
    if target.resolve() == Path.cwd().resolve() or os.path.ismount(target):
        # the results are published by renaming the staging folder onto the target, which
        # the system refuses for the working folder (EBUSY) and for a mount point
        what = "the current folder" if target.resolve() == Path.cwd().resolve() else \
            "a mount point"
        raise ResultsError(f"{name}: is {what}, which a finished run cannot be renamed onto; "
                           "give the name of a new folder (e.g. --out ./results-1)")
    if not os.access(target, os.W_OK):  # an existing folder the user may not write to
        raise ResultsError(f"{name}: is read-only (no write permission); nothing was run")
    entries = sorted(p.name for p in target.iterdir())
    if not entries:
        return
    if not overwrite:
        what = "a finished results folder" if is_complete(target) else \
            f"not empty ({len(entries)} entries)"
        raise ResultsError(f"{name}: is {what}; choose another --out, or add --overwrite to "
                           "replace it as a whole")
    # only the files gslam's marker lists (or, unmarked, names gslam writes) may be replaced;
    # a COMPLETE that gslam did not write is the user's file like any other
    listed = _marker_files(target)
    ours = listed | {MARKER} if listed is not None else RESULT_FILES - {MARKER}
    foreign = [e for e in entries if e not in ours]
    if foreign:
        shown = ", ".join(foreign[:5]) + (", ..." if len(foreign) > 5 else "")
        raise ResultsError(f"{name}: holds files gslam does not write ({shown}); --overwrite "
                           "only replaces a gslam results folder: choose another --out")


def _write_marker(staging: Path, command: str) -> None:
    files = {p.name: p.stat().st_size for p in sorted(staging.iterdir()) if p.is_file()}
    text = json.dumps({"format": MARKER_FORMAT, "command": command,
                       "finished": datetime.datetime.now(datetime.timezone.utc).isoformat(
                           timespec="seconds"),
                       "files": files}, indent=2)
    (staging / MARKER).write_text(text + "\n")


def _publish(staging: Path, target: Path, name: str, overwrite: bool) -> None:
    """Rename ``staging`` to ``target`` (replacing an old results folder when ``overwrite``).
    When another command took ``target`` meanwhile, ResultsError says where the results are."""
    old = None
    if overwrite and target.is_dir() and any(target.iterdir()):
        old = Path(tempfile.mkdtemp(prefix=f".{target.name}.old-", dir=target.parent))
        os.rename(target, old / "results")
    try:
        os.rename(staging, target)  # atomic; replaces an empty directory, never a full one
    except OSError as err:
        if err.errno not in (errno.ENOTEMPTY, errno.EEXIST, errno.ENOTDIR):
            raise
        if old is not None:
            os.rename(old / "results", target)
            old.rmdir()
        raise _Taken(f"{name}: another command wrote there while this one ran; these "
                           f"results are complete and kept in {staging}") from err
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def results_folder(out: str | Path | None, kind: str, overwrite: bool = False,
                   command: str | None = None) -> Iterator[Staged]:
    """Yield a staging folder (``Staged``) for a command's outputs; on success mark it complete
    and rename it to ``out`` (default ``results/<kind>-<time>``). ResultsError, before the
    command does any work, when ``out`` exists and is not an empty directory (without
    ``overwrite``) or when nothing can be written beside it. When the command fails or is
    interrupted, the staging folder and the folders created here are removed: nothing is left
    under ``out``.
    """
    if out is not None:
        target, name = _follow_link(Path(out), f"--out {out}")
    else:
        stamp = time.strftime(f"{kind}-%Y%m%d-%H%M%S")
        target = Path("results") / stamp
        for i in range(2, 1000):
            if not target.exists():
                break
            target = Path("results") / f"{stamp}-{i}"
        name = f"results directory {target}"
    _check_target(target, name, overwrite)
    parent = target.absolute().parent
    new = [p for p in (parent, *parent.parents) if not p.exists()]  # deepest first
    try:
        parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{target.name}.partial-", dir=parent))
    except OSError as err:
        _remove_empty(new)
        raise ResultsError(f"{name}: cannot write there ({err.strerror or err}); nothing was "
                           "run") from err
    try:
        with sigterm_as_exit():
            yield Staged(staging, target, name)
        try:
            _write_marker(staging, command or f"gslam {kind}")
        except OSError as err:
            raise ResultsError(f"{name}: cannot write the results ({err}); nothing was "
                               f"written to {target}") from err
        _publish(staging, target, name, overwrite)
    except BaseException as err:
        if not isinstance(err, _Taken):
            shutil.rmtree(staging, ignore_errors=True)
            _remove_empty(new)
        raise


@contextlib.contextmanager
def writing(folder: Staged) -> Iterator[None]:
    """Writing a command's files into its staging folder: an OSError (a full disk) becomes a
    ResultsError naming the folder (the staging folder is then removed, nothing published)."""
    try:
        yield
    except OSError as err:
        raise ResultsError(f"{folder.name}: cannot write the results ({err.strerror or err}); "
                           f"nothing was written to {folder.target}") from err


def _remove_empty(folders: list[Path]) -> None:
    """Remove the folders this module created (deepest first) while they are empty."""
    for folder in folders:
        if not folder.is_dir() or any(folder.iterdir()):
            break
        folder.rmdir()
