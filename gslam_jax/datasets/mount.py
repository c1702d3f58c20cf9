"""The camera mount of an image source: where the left camera sits on the robot ([rig]).

A mount is the 4x4 ``T_robot_cam`` of ``vo.frontend.run_frontend``: camera optical frame
(OpenCV: x right, y down, z forward) to the robot frame (x forward, y left, z up, origin on the
ground under the robot). In values (``mount_matrix``) it is

    T = [R | t],  R = Rz(yaw) Ry(pitch) Rx(roll) CAM_TO_ROBOT_AXES,  t = (forward, lateral, height)

with the angles about the robot's axes: a camera with all three zero looks along the robot's x
axis, level; positive pitch turns it nose down (as ``sim.render.camera_mounts`` and the paper's
LAGR robot), positive roll lowers its right side, positive yaw turns it left. The mount describes
the left camera as it sits on the robot (the raw camera where images are rectified by the
source: the source adds the rectifying rotation).

``camera_mount(config, default, where)`` is the mount a source uses: the source's ``default``
with the config's ``[rig]`` values applied. ``matrix`` replaces the whole default. Otherwise
the default is written as values (:func:`mount_values`) and each [rig] value that is not 0
replaces its own: ``height`` the camera's height t_z, ``forward`` t_x, ``lateral`` t_y,
``pitch``/``roll``/``yaw`` that angle, the others keeping the default's. So a [rig] 0 keeps the
source's value; a zero the default does not have (a level camera where the source's is pitched)
takes ``matrix``.

A mount set by [rig] is checked for the terrain being in view (:func:`check_ground_in_view`):
the front-end maps the ground ahead, so a camera whose optical axis points more than
``MAX_ELEVATION_DEG`` above the horizon (e.g. ``rig.pitch = -80``, nose up) is refused naming
the key, and one pointing above the horizon at all is warned about.
"""

from __future__ import annotations

import warnings

import numpy as np

from gslam_jax.config import Config, ConfigError
from gslam_jax.vo.geometry import CAM_TO_ROBOT_AXES, make_transform

__all__ = ["camera_mount", "check_ground_in_view", "mount_matrix", "mount_values",
           "MOUNT_KEYS", "MAX_ELEVATION_DEG"]

MOUNT_KEYS = ("height", "pitch", "roll", "yaw", "forward", "lateral")
# The optical axis may point at most this far above the horizon: a camera's vertical field of
# view is rarely wider than 60 degrees, so beyond it the lower edge of the image, too, looks
# above the horizon and no ground is in view.
MAX_ELEVATION_DEG = 30.0


def _axis_rotations(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Rz(yaw) Ry(pitch) Rx(roll), right-handed about the robot's z, y and x (radians)."""
    cy, sy, cp, sp, cr, sr = (np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch),
                              np.cos(roll), np.sin(roll))
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return rz @ ry @ rx


def mount_matrix(height: float, pitch: float = 0.0, roll: float = 0.0, yaw: float = 0.0,
                 forward: float = 0.0, lateral: float = 0.0) -> np.ndarray:
    """4x4 camera-to-robot mount of a camera ``height`` m above the ground, ``forward`` and
    ``lateral`` m along the robot's x and y, turned by ``yaw``, ``pitch`` (nose down positive)
    and ``roll`` (degrees; see the module docstring)."""
    y, p, r = np.deg2rad([yaw, pitch, roll])
    rot = _axis_rotations(y, p, r) @ CAM_TO_ROBOT_AXES
    return make_transform(rot, [forward, lateral, height])


def mount_values(mount: np.ndarray) -> dict[str, float]:
    """The values of a mount (``MOUNT_KEYS``, angles in degrees): the inverse of
    :func:`mount_matrix` (pitch in [-90, 90]; at +-90 the yaw takes all of the turn about the
    vertical)."""
    m = np.asarray(mount, np.float64)
    r = m[:3, :3] @ CAM_TO_ROBOT_AXES.T  # Rz(yaw) Ry(pitch) Rx(roll)
    pitch = np.arcsin(np.clip(-r[2, 0], -1.0, 1.0))
    if abs(r[2, 0]) < 1.0 - 1e-12:
        yaw, roll = np.arctan2(r[1, 0], r[0, 0]), np.arctan2(r[2, 1], r[2, 2])
    else:  # gimbal lock: roll folded into yaw
        yaw, roll = np.arctan2(-r[0, 1], r[1, 1]), 0.0
    deg = np.rad2deg([pitch, roll, yaw])
    return {"height": float(m[2, 3]), "pitch": float(deg[0]), "roll": float(deg[1]),
            "yaw": float(deg[2]), "forward": float(m[0, 3]), "lateral": float(m[1, 3])}


def camera_mount(config: Config, default: np.ndarray | None, where: str) -> np.ndarray:
    """The mount (4x4 camera to robot) a source uses: its ``default`` with the config's [rig]
    values applied (see the module docstring); the default itself, unchanged, when [rig] is
    empty. ``default`` None: the source has none, so [rig] must give ``height`` or ``matrix``
    (ConfigError naming ``where``, e.g. "--source stereo DIR")."""
    rig = config.rig
    if rig.matrix:
        return np.array(rig.matrix, np.float64).reshape(4, 4)
    if default is None:
        if not rig.height:
            raise ConfigError(f"{where}: the camera mount is not known: give [rig] height (m, "
                              "camera above the ground) and pitch (deg, nose down), or [rig] "
                              "matrix (the 4x4 camera-to-robot transform); docs/formats.md")
        values = dict.fromkeys(MOUNT_KEYS, 0.0)
    elif rig.is_default():
        return np.array(default, np.float64)
    else:
        values = mount_values(default)
    values.update({k: getattr(rig, k) for k in MOUNT_KEYS if getattr(rig, k)})
    mount = mount_matrix(**values)
    check_ground_in_view(mount, config, where)
    return mount


def check_ground_in_view(mount: np.ndarray, config: Config, where: str) -> None:
    """ConfigError when the camera of ``mount`` looks more than MAX_ELEVATION_DEG above the
    horizon (no ground in view), a warning when it looks above it at all; the message names
    the [rig] keys that set it and the plausible pitch."""
    axis = np.asarray(mount, np.float64)[:3, 2]  # the optical axis (camera z) in robot axes
    elevation = float(np.degrees(np.arcsin(np.clip(axis[2], -1.0, 1.0))))
    if elevation <= 0.0:
        return
    rig = config.rig
    keys = "[rig] matrix" if rig.matrix else \
        ", ".join(f"rig.{k} = {getattr(rig, k):g}" for k in ("pitch", "roll") if getattr(rig, k))
    keys = keys or "the source's mount"
    text = (f"{where}: {keys} points the left camera {elevation:.0f} degrees above the "
            "horizon; Gamma-SLAM maps the ground ahead, which a camera needs in view: pitch is "
            "positive nose down (a level camera 0, a ground robot's typically 0 to 30)")
    if elevation > MAX_ELEVATION_DEG:
        raise ConfigError(f"{text}; more than {MAX_ELEVATION_DEG:g} degrees up, no ground is in "
                          "view. Check the sign of rig.pitch")
    warnings.warn(f"{text}; only the lower part of the image sees the ground", stacklevel=3)
