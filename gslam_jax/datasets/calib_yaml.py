"""Reading calibration YAML (OpenCV FileStorage, ROS camera_info, EuRoC sensor.yaml) with errors
that name the file and field.

A matrix field may be a flat list of numbers, or a map holding ``data`` (ROS ``{rows, cols,
data}``, OpenCV ``!!opencv-matrix``). Files need no ``%YAML`` header.
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from gslam_jax.vo.calib import CalibrationError

__all__ = ["open_yaml", "field_node", "numbers", "text"]


def open_yaml(path: Path) -> cv2.FileStorage:
    """The open FileStorage of ``path``; CalibrationError naming it when it is missing or not
    YAML (with OpenCV's line number where it gives one)."""
    if not path.is_file():
        raise CalibrationError(f"{path}: calibration file is missing")
    try:  # OpenCV raises (cv2.error, or SystemError from its bindings) on text it cannot parse
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as err:
        message = str(err.__cause__ if err.__cause__ is not None else err)
        found = re.search(r"\((\d+)\): ([^'\n]*)", message)
        detail = f"line {found[1]}: {found[2]}" if found else message.strip().splitlines()[-1]
        raise CalibrationError(f"{path}: not a readable YAML file ({detail})") from err
    if not fs.isOpened():
        raise CalibrationError(f"{path}: not a readable YAML file")
    return fs


def field_node(node: cv2.FileNode, names: tuple[str, ...]) -> tuple[cv2.FileNode | None, str]:
    """The first of ``names`` present in the map ``node`` and its name (None, names[0]: none)."""
    for name in names:
        child = node.getNode(name)
        if not (child.empty() or child.isNone()):
            return child, name
    return None, names[0]


def numbers(node: cv2.FileNode | None, field: str, count: int | None, path: Path,
            *, counts: tuple[int, ...] = ()) -> np.ndarray:
    """The finite numbers of a field (a list, or a map's ``data`` list): ``count`` of them (None:
    any number, or one of ``counts``). CalibrationError naming ``path`` and ``field`` for a
    missing field, a wrong count or an entry that is not a finite number."""
    if node is None or node.empty() or node.isNone():
        raise CalibrationError(f"{path}: missing field '{field}'")
    if node.isMap():
        node = node.getNode("data")
        if node.empty():
            raise CalibrationError(f"{path}: field '{field}' has no 'data' list")
    items = [node.at(i) for i in range(node.size())] if node.isSeq() else []
    if (count is not None and len(items) != count) or (counts and len(items) not in counts):
        wanted = count if count is not None else " or ".join(map(str, counts))
        raise CalibrationError(f"{path}: field '{field}' has {len(items)} numbers, expected "
                               f"{wanted}")
    for i, item in enumerate(items):
        if not (item.isReal() or item.isInt()):
            shown = f"{item.string()!r} " if item.isString() else ""
            raise CalibrationError(f"{path}: field '{field}' entry {i}: {shown}is not a number")
    vals = np.array([item.real() for item in items], dtype=np.float64)
    if not np.all(np.isfinite(vals)):
        raise CalibrationError(f"{path}: field '{field}' has a non-finite number: "
                               f"{vals.tolist()}")
    return vals


def text(node: cv2.FileNode | None) -> str:
    """A string field's text ('' where absent)."""
    return "" if node is None or node.empty() or node.isNone() else node.string()
