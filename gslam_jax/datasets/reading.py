"""What every dataset adapter reads the same way: text tables of numbers, grey images, time
stamps that must increase, and quaternions. Errors name the file (and line)."""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from gslam_jax.errors import DatasetError
from gslam_jax.vo.calib import ImageError

__all__ = ["Table", "read_table", "read_image", "first_not_increasing", "quat_to_matrix",
           "pose_jump"]


def read_image(path: Path) -> np.ndarray:
    """Grey image or ImageError naming the file."""
    if not path.is_file():
        raise ImageError(f"{path}: image file is missing")
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise ImageError(f"{path}: not a readable image (corrupt or unknown format)")
    return img


class Table(NamedTuple):
    """Numbers of a text table: ``data`` [rows, columns] float64, ``lines`` [rows] 1-based line
    number of each row, ``stamps`` [rows] int64 first column (exact; only when asked)."""

    data: np.ndarray
    lines: np.ndarray
    stamps: np.ndarray | None = None


def read_table(path: Path, columns: int, delimiter: str | None = None, *, at_least: bool = False,
               int_first: bool = False) -> Table:
    """Rows of finite numbers ('#' starts a comment; blank lines are skipped).

    Every row has ``columns`` numbers (``at_least``: that many or more, the same in every row);
    ``int_first``: the first column is an integer (e.g. nanoseconds), also returned exactly in
    ``stamps``. ValueError naming the file and line of the first bad row.
    """
    rows: list[list[float]] = []
    lines: list[int] = []
    stamps: list[int] = []
    for n, line in enumerate(Path(path).read_text(errors="replace").splitlines(), 1):
        body = line.split("#", 1)[0].strip()
        if not body:
            continue
        fields = [f.strip() for f in body.split(delimiter)]
        if rows and len(fields) != len(rows[0]):
            raise DatasetError(f"{path}:{n}: {len(fields)} numbers, but {len(rows[0])} on line "
                               f"{lines[0]}")
        if not rows and (len(fields) < columns if at_least else len(fields) != columns):
            raise DatasetError(f"{path}:{n}: expected {columns}{' or more' if at_least else ''} "
                               f"numbers, got {len(fields)}")
        row = []
        for f in fields:
            try:
                row.append(float(f))
            except ValueError:
                raise DatasetError(f"{path}:{n}: {f!r} is not a number") from None
        if not np.all(np.isfinite(row)):
            raise DatasetError(f"{path}:{n}: non-finite number in {body!r}")
        if int_first:
            try:
                stamps.append(int(fields[0]))
            except ValueError:
                raise DatasetError(f"{path}:{n}: {fields[0]!r} is not an integer "
                                   "timestamp") from None
        rows.append(row)
        lines.append(n)
    if not rows:
        raise DatasetError(f"{path}: no data rows")
    return Table(np.array(rows, np.float64), np.array(lines, np.int64),
                 np.array(stamps, np.int64) if int_first else None)


def first_not_increasing(values: np.ndarray) -> int | None:
    """Index i >= 1 of the first value not after values[i - 1], or None when strictly
    increasing (time stamps of a log, in file order)."""
    back = np.flatnonzero(np.diff(values) <= 0)
    return int(back[0]) + 1 if back.size else None


def quat_to_matrix(q: np.ndarray, scalar_last: bool = False) -> np.ndarray:
    """Rotation matrices [..., 3, 3] of quaternions [..., 4], each normalised first: (w, x, y, z)
    (EuRoC, ROS messages in that order), or with ``scalar_last`` (x, y, z, w) (TUM files)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / (np.linalg.norm(q) if q.ndim == 1 else np.linalg.norm(q, axis=-1, keepdims=True))
    if scalar_last:
        x, y, z, w = np.moveaxis(q, -1, 0)
    else:
        w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], axis=-2)


def pose_jump(xy: np.ndarray, lines: np.ndarray, path: Path | str, factor: float = 50.0,
              at_least: float = 10.0) -> str | None:
    """A note naming the first step of a pose file's positions ``xy`` [N, 2|3] (rows at file
    ``lines``) longer than ``factor`` times the median moving step and ``at_least`` metres (a
    spike, or a clock gap, in a recorded path), or None. Informational: such a file is read
    as it is."""
    steps = np.linalg.norm(np.diff(np.asarray(xy, np.float64), axis=0), axis=1)
    moving = steps[steps > 1e-6]
    if not moving.size:
        return None
    limit = max(factor * float(np.median(moving)), at_least)
    far = np.flatnonzero(steps > limit)
    if not far.size:
        return None
    i = int(far[0]) + 1
    more = f" ({far.size - 1} more such steps)" if far.size > 1 else ""
    return (f"{path}:{int(lines[i])}: pose {i} is {steps[i - 1]:.1f} m from the one before, "
            f"where the median step is {float(np.median(moving)):.3g} m{more}: a spike or a gap "
            "in the file? It is used as it is")
