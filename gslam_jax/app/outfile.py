"""One output file (a JSON, a plot, a TOML): checked before the work, written atomically.

Every file a ``gslam`` command writes (``--save-run``, ``--viewer-save``, ``view --save``,
``--json``, ``--plot``, ``config --out``, ``fit-motion --out``) goes through here, as the
results folders of ``--out`` go through ``results``. ``check_output_file`` refuses, before a
command runs, an existing file unless the command's ``--overwrite`` is given, a path that is a
folder, whose folder does not exist, or where nothing can be written (probed by creating a file
there: ``os.access`` says yes to root on a read-only mount). ``atomic_file`` yields a temporary path beside the
target, with the target's suffix so that a plotter picks the format from it, and renames it
onto the target once written: a full disk or an interrupted write leaves the old file or
none, never a truncated one. The errors are ``OutputFileError``, naming the option and path.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Iterator

from gslam_jax.errors import InputError

__all__ = ["OutputFileError", "check_output_file", "staged_file", "atomic_file",
           "write_text_atomic"]


class OutputFileError(InputError):
    """An output file cannot be written there: the message names the option and the path."""


def check_output_file(path: str | Path, option: str, overwrite: bool = False) -> None:
    """OutputFileError, before any work, when ``option`` (e.g. "--json") cannot write ``path``,
    or ``path`` exists and ``overwrite`` (the command's ``--overwrite``) is not given."""
    path = Path(path)
    name = f"{option} {path}"
    if path.is_dir():
        raise OutputFileError(f"{name}: is a directory; give a file name")
    if not overwrite and (path.exists() or path.is_symlink()):
        raise OutputFileError(f"{name}: exists (--overwrite replaces it); nothing was run")
    parent = path.absolute().parent
    if not parent.is_dir():
        raise OutputFileError(f"{name}: folder {parent} does not exist")
    try:
        fd, probe = tempfile.mkstemp(prefix=f".{path.name}.", dir=parent)
    except OSError as err:
        raise OutputFileError(f"{name}: cannot write in {parent} ({err.strerror or err}); "
                              "nothing was run") from err
    os.close(fd)
    os.unlink(probe)


@contextlib.contextmanager
def staged_file(path: str | Path, option: str) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` for a file written over a whole command (e.g. a
    viewer's recording); rename it onto ``path`` in one step when the block ends without an
    error, remove it otherwise (the block's error passes unchanged). OutputFileError when the
    temporary cannot be made or renamed."""
    path = Path(path)
    name = f"{option} {path}"
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.partial-", suffix=path.suffix,
                                   dir=path.absolute().parent)
    except OSError as err:
        raise OutputFileError(f"{name}: cannot write there ({err.strerror or err})") from err
    os.close(fd)
    try:
        yield Path(tmp)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    try:
        os.chmod(tmp, 0o666 & ~_umask())  # as open() would create it (mkstemp makes 0600)
        os.replace(tmp, path)
    except OSError as err:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise OutputFileError(f"{name}: cannot write it ({err.strerror or err}); nothing was "
                              "written there") from err


@contextlib.contextmanager
def atomic_file(path: str | Path, option: str) -> Iterator[Path]:
    """Yield a temporary path to write; on success rename it onto ``path`` in one step
    (``staged_file``). An OSError while writing (e.g. a full disk) becomes OutputFileError,
    the temporary removed."""
    try:
        with staged_file(path, option) as tmp:
            yield tmp
    except OSError as err:
        raise OutputFileError(f"{option} {path}: cannot write it ({err.strerror or err}); "
                              "nothing was written there") from err


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_text_atomic(path: str | Path, text: str, option: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` through ``atomic_file``, flushed to disk first."""
    with atomic_file(path, option) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
