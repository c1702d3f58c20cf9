"""Which topics of a bag the rosbag source reads (by role), and stereo pairs by timestamp.

Roles (``ROLES``): ``left``, ``right`` (``sensor_msgs/Image`` or ``CompressedImage``),
``left_info``, ``right_info`` (``sensor_msgs/CameraInfo``), and the optional ``wheel``
(``nav_msgs/Odometry``), ``imu`` (``sensor_msgs/Imu``) and ``ground_truth``
(``geometry_msgs/PoseStamped``, ``nav_msgs/Odometry`` or ``geometry_msgs/TransformStamped``).

A role given (``--topic ROLE=NAME``; ``ROLE=`` for none, optional roles only) is used as given.
Otherwise it is picked when exactly one topic is a candidate:

- left / right: the image topics whose name has a left / right hint as a word ("left", "cam0",
  "camera0", "infra1", "image_0" / "right", "cam1", "camera1", "infra2", "image_1");
- left_info / right_info: the CameraInfo topics in the deepest namespace holding the image topic
  (``/cam0/camera_info`` for ``/cam0/image_raw``), narrowed by the side's hint where several;
- ground_truth: the pose topics whose name says so ("ground_truth", "groundtruth", "gt",
  "truth", "vicon", "mocap", "optitrack", "leica");
- wheel: the other Odometry topics (narrowed to those named "wheel" where several);
- imu: the Imu topics.

None or several candidates for a required role, or several for an optional one, is a
DatasetError listing the candidates (or the bag's topics) and the ``--topic`` to give.
"""

from __future__ import annotations

import re
from typing import Mapping, NamedTuple

import numpy as np

from gslam_jax.config import ConfigError
from gslam_jax.datasets.rosbag_msgs import (CAMERA_INFO, COMPRESSED, IMAGE, IMU, ODOMETRY, POSE,
                                            TRANSFORM)
from gslam_jax.errors import DatasetError

__all__ = ["ROLES", "REQUIRED", "TopicInfo", "check_roles", "pick_topics", "rectified_topic",
           "Pairing", "pair_stamps"]

ROLES: dict[str, tuple[str, ...]] = {
    "left": (IMAGE, COMPRESSED), "right": (IMAGE, COMPRESSED),
    "left_info": (CAMERA_INFO,), "right_info": (CAMERA_INFO,),
    "wheel": (ODOMETRY,), "imu": (IMU,), "ground_truth": (POSE, ODOMETRY, TRANSFORM)}
REQUIRED = ("left", "right", "left_info", "right_info")


def _word(pattern: str) -> re.Pattern:
    """``pattern`` as a whole word of a topic name (words split by anything not alphanumeric)."""
    return re.compile(rf"(?<![a-z0-9])(?:{pattern})(?![a-z0-9])")


HINTS = {"left": _word(r"left|cam_?0|camera_?0|infra_?1|image_?0"),
         "right": _word(r"right|cam_?1|camera_?1|infra_?2|image_?1"),
         "ground_truth": _word(r"ground_?truth|gt|truth|vicon|mocap|optitrack|leica"),
         "wheel": _word(r"wheels?")}


RECTIFIED = _word("rect")  # image_proc's image_rect, image_rect_color; RealSense's image_rect_raw


def rectified_topic(topic: str) -> bool:
    """Images rectified already: a topic named with the word "rect" (``image_rect``,
    ``image_rect_color``, ...), whose CameraInfo still describes the raw camera."""
    return RECTIFIED.search(topic.lower()) is not None


class TopicInfo(NamedTuple):
    """A topic of the bag: its message type and message count."""

    msgtype: str | None
    count: int


def _hinted(role: str, names: list[str]) -> list[str]:
    return [n for n in names if HINTS[role].search(n.lower())]


def _listing(topics: Mapping[str, TopicInfo], types: tuple[str, ...] | None = None) -> str:
    rows = [f"{name} ({(info.msgtype or '?').replace('/msg/', '/')}, {info.count})"
            for name, info in sorted(topics.items())
            if types is None or info.msgtype in types]
    return ", ".join(rows) if rows else "none"


def check_roles(given: Mapping[str, str | None]) -> None:
    """ConfigError for a role that is not one of ``ROLES`` or a required role given as none."""
    for role, name in given.items():
        if role not in ROLES:
            raise ConfigError(f"--topic {role}=...: unknown role {role!r}; roles: "
                              f"{', '.join(ROLES)}")
        if not name and role in REQUIRED:
            raise ConfigError(f"--topic {role}=: the {role} topic is required (name it, or "
                              "leave it out to pick it automatically)")


def _info_candidates(image: str, infos: list[str], side: str) -> list[str]:
    """CameraInfo topics in the deepest namespace holding ``image``, then by the side's hint."""
    def depth(info: str) -> int:
        ns = info.rsplit("/", 1)[0]
        return len(ns) if image.startswith(ns + "/") else -1
    best = max((depth(i) for i in infos), default=-1)
    found = [i for i in infos if best >= 0 and depth(i) == best]
    return _hinted(side, found) if len(found) > 1 and _hinted(side, found) else found


def pick_topics(topics: Mapping[str, TopicInfo], given: Mapping[str, str | None],
                bag: str) -> dict[str, str | None]:
    """The topic of each role (None: an optional role not there); see the module docstring."""
    check_roles(given)
    of_type = {role: [n for n, i in topics.items() if i.msgtype in types]
               for role, types in ROLES.items()}
    picked: dict[str, str | None] = {}
    for role, name in given.items():
        if not name:
            picked[role] = None
            continue
        if name not in topics:
            raise DatasetError(f"{bag}: --topic {role}={name}: no such topic; the bag's "
                               f"{role} candidates: {_listing(topics, ROLES[role])} (all "
                               f"topics: {_listing(topics)})")
        if topics[name].msgtype not in ROLES[role]:
            raise DatasetError(f"{bag}: --topic {role}={name}: it carries "
                               f"{topics[name].msgtype}, not {' or '.join(ROLES[role])}")
        picked[role] = name

    def choose(role: str, found: list[str], everything: list[str]) -> None:
        if role in picked:
            return
        if len(found) == 1:
            picked[role] = found[0]
            return
        if not found and role not in REQUIRED:
            picked[role] = None
            return
        listed = _listing({n: topics[n] for n in (found or everything)})
        what = "candidates" if found else f"{' or '.join(ROLES[role])} topics"
        none = f", or --topic {role}= for none" if role not in REQUIRED else ""
        raise DatasetError(f"{bag}: {'no' if not found else len(found)} candidate(s) for the "
                           f"{role} topic; {what}: {listed}: name it with --topic "
                           f"{role}=NAME{none}")

    images = of_type["left"]
    for side in ("left", "right"):
        choose(side, _hinted(side, images), images)
    if picked["left"] == picked["right"]:
        raise DatasetError(f"{bag}: {picked['left']} is both the left and the right image topic; "
                           "name them with --topic left=NAME --topic right=NAME")
    infos = of_type["left_info"]
    for side in ("left", "right"):
        choose(f"{side}_info", _info_candidates(picked[side] or "", infos, side), infos)
    truth = [n for n in of_type["ground_truth"] if HINTS["ground_truth"].search(n.lower())]
    choose("ground_truth", truth, of_type["ground_truth"])
    odom = [n for n in of_type["wheel"] if n != picked["ground_truth"] and n not in truth]
    choose("wheel", _hinted("wheel", odom) if len(odom) > 1 and _hinted("wheel", odom) else odom,
           odom)
    choose("imu", of_type["imu"], of_type["imu"])
    return {role: picked[role] for role in ROLES}


class Pairing(NamedTuple):
    """Stereo pairs by timestamp: ``left`` [N] and ``right`` [N] indices into the two (sorted)
    stamp lists, and the stamps (ns) of the frames of each side left without a partner."""

    left: np.ndarray
    right: np.ndarray
    unmatched_left: np.ndarray
    unmatched_right: np.ndarray


def _nearest(values: np.ndarray, to: np.ndarray) -> np.ndarray:
    """Index of the value of sorted ``values`` nearest each of ``to`` (the earlier on a tie)."""
    j = np.clip(np.searchsorted(values, to), 1, max(len(values) - 1, 1))
    if len(values) == 1:
        return np.zeros(len(to), np.int64)
    return np.where(np.abs(values[j - 1] - to) <= np.abs(values[j] - to), j - 1, j)


def pair_stamps(left: np.ndarray, right: np.ndarray, tolerance_ns: int) -> Pairing:
    """Pairs of left and right frames (sorted int64 stamps, ns) that are each other's nearest
    and at most ``tolerance_ns`` apart; every other frame is reported as unmatched."""
    left, right = np.asarray(left, np.int64), np.asarray(right, np.int64)
    if not (len(left) and len(right)):
        return Pairing(np.zeros(0, np.int64), np.zeros(0, np.int64), left, right)
    j = _nearest(right, left)
    back = _nearest(left, right)
    ok = (back[j] == np.arange(len(left))) & (np.abs(right[j] - left) <= tolerance_ns)
    li, ri = np.flatnonzero(ok), j[ok]
    lone_right = np.ones(len(right), bool)
    lone_right[ri] = False
    return Pairing(li, ri, left[~ok], right[lone_right])
