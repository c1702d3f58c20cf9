"""The camera mount ([rig], datasets.mount) against independent constructions: SciPy's Euler
rotations, and the ground seen by a pitched camera by plane trigonometry."""

from __future__ import annotations

import dataclasses
import tomllib

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gslam_jax.config import Config, ConfigError, apply_overrides, config_to_toml, parse_config
from gslam_jax.datasets.mount import camera_mount, mount_matrix, mount_values
from gslam_jax.datasets.registry import Source, check_source
from gslam_jax.sim.render import RenderParams, camera_mounts

# Camera axes (x right, y down, z forward) in robot axes (x forward, y left, z up), by hand.
AXES = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _rig(**values) -> Config:
    return apply_overrides(Config(), [f"rig.{k}={v}" for k, v in values.items()])


@pytest.mark.parametrize("yaw, pitch, roll", [(0, 0, 0), (0, 16, 0), (35, 16, 0),
                                              (-20, 10, 3), (170, -45, -120)])
def test_mount_matrix_is_scipy_intrinsic_zyx(yaw, pitch, roll):
    m = mount_matrix(1.3, pitch, roll, yaw, 0.4, -0.2)
    # nose down is a positive turn about the robot's y axis (y left): x goes to -z
    r = Rotation.from_euler("ZYX", [yaw, pitch, roll], degrees=True).as_matrix()
    assert np.allclose(m[:3, :3], r @ AXES, atol=1e-12)
    assert np.allclose(m[:3, 3], [0.4, -0.2, 1.3]) and np.allclose(m[3], [0, 0, 0, 1])
    values = mount_values(m)
    assert values == pytest.approx(dict(height=1.3, pitch=pitch, roll=roll, yaw=yaw, forward=0.4,
                                        lateral=-0.2), abs=1e-9)


@pytest.mark.parametrize("pitch, below", [(16.0, 0.0), (16.0, 10.0), (30.0, -8.0)])
def test_pitched_mount_puts_the_ground_it_sees_at_z_zero(pitch, below):
    """A ray ``below`` degrees under the optical axis of a camera h above the ground pitched
    down by ``pitch`` meets the ground h / tan(pitch + below) ahead, at range
    h / sin(pitch + below) along the ray."""
    h = 1.1
    depression = np.deg2rad(pitch + below)
    a = np.deg2rad(below)
    ray = np.array([0.0, np.sin(a), np.cos(a)])  # camera frame: y down
    point_cam = ray * h / np.sin(depression)
    point = mount_matrix(h, pitch) @ np.append(point_cam, 1.0)
    assert point[:3] == pytest.approx([h / np.tan(depression), 0.0, 0.0], abs=1e-12)


def test_the_renderer_mount_is_a_mount_matrix():
    """sim.render's pair 0 (yawed left, pitched down, left eye half a baseline left)."""
    p = RenderParams()
    left = camera_mounts(p)[0][0]
    yaw, pitch = np.rad2deg([p.camera_yaw, p.camera_pitch])
    half = 0.5 * p.baseline
    expect = mount_matrix(p.camera_height, pitch, 0.0, yaw, -half * np.sin(np.deg2rad(yaw)),
                          half * np.cos(np.deg2rad(yaw)))
    assert np.allclose(left, expect, atol=1e-12)


def test_camera_mount_applies_each_rig_value_to_the_default():
    default = mount_matrix(1.0, 16.0, 0.0, 35.0, 0.02, 0.05)
    assert np.array_equal(camera_mount(Config(), default, "x"), default)
    assert np.allclose(camera_mount(_rig(height=1.5), default, "x"),
                       mount_matrix(1.5, 16.0, 0.0, 35.0, 0.02, 0.05), atol=1e-12)
    assert np.allclose(camera_mount(_rig(pitch=25, lateral=0.3), default, "x"),
                       mount_matrix(1.0, 25.0, 0.0, 35.0, 0.02, 0.3), atol=1e-12)
    assert np.allclose(camera_mount(_rig(height=2, pitch=-5, roll=1, yaw=-3, forward=0.5,
                                         lateral=-0.1), default, "x"),
                       mount_matrix(2.0, -5.0, 1.0, -3.0, 0.5, -0.1), atol=1e-12)
    full = mount_matrix(0.7, 12.0, 2.0, 4.0)
    rows = str(full.tolist())
    assert np.allclose(camera_mount(_rig(matrix=rows), default, "x"), full)
    assert np.allclose(camera_mount(_rig(matrix=str(full.ravel().tolist())), None, "x"), full)


def test_a_source_without_a_default_needs_the_height_or_matrix():
    with pytest.raises(ConfigError, match=r"--source stereo D: .*\[rig\] height"):
        camera_mount(_rig(pitch=10), None, "--source stereo D")
    assert np.allclose(camera_mount(_rig(height=0.8, pitch=10), None, "w"),
                       mount_matrix(0.8, 10.0))


@pytest.mark.parametrize("override, key", [
    ("rig.height=-0.5", "height"), ("rig.pitch=95", "pitch"), ("rig.roll=-200", "roll"),
    ("rig.yaw=181", "yaw"), ("rig.forward=nan", "forward"), ("rig.matrix=[1, 2, 3]", "matrix"),
    ("rig.matrix=[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,1,1]]", "matrix"),
    ("rig.matrix=[[1,0,0,0],[0,-1,0,0],[0,0,1,0],[0,0,0,1]]", "matrix"),
    ("rig.matrix=\"x\"", "matrix")])
def test_bad_rig_values_are_named(override, key):
    with pytest.raises(ConfigError, match=rf"\[rig\] {key}"):
        apply_overrides(Config(), [override])


def test_matrix_and_values_are_exclusive():
    with pytest.raises(ConfigError, match=r"\[rig\] matrix and height, pitch are exclusive"):
        parse_config({"rig": {"height": 1.0, "pitch": 5.0, "matrix": np.eye(4).tolist()}},
                     "my.toml")


def test_rig_round_trips_through_toml():
    config = _rig(matrix=str(mount_matrix(1.0, 10.0).tolist()))
    back = parse_config(tomllib.loads(config_to_toml(config)))
    assert back == config and len(back.rig.matrix) == 16
    config = _rig(height=1.2, pitch=12.5)
    assert parse_config(tomllib.loads(config_to_toml(config))) == config
    assert parse_config(tomllib.loads(config_to_toml(Config()))).rig.matrix == ()


def test_rig_is_refused_where_there_are_no_images():
    with pytest.raises(ConfigError, match=r"\[rig\] height, yaw: .*--source sim has none"):
        check_source(Source(source="sim"), _rig(height=1.0, yaw=3))
    check_source(Source(source="sim-stereo"), _rig(height=1.0))
    assert dataclasses.asdict(Config().rig)["matrix"] == ()


def test_configuration_reference_lists_every_rig_key_with_its_default():
    import re
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[1] / "docs" / "configuration.md").read_text()
    section = doc.split("### `[rig]`", 1)[1].split("\n\n| source |", 1)[0]
    rows = dict(re.findall(r"^\| `rig\.(\w+)` \| ([^|]+) \|", section, re.MULTILINE))
    assert set(rows) == set(dataclasses.asdict(Config().rig))
    for key, text in rows.items():
        value = tomllib.loads(f"v = {text.strip().strip('`')}")["v"]
        assert value == list(getattr(Config().rig, key)) if key == "matrix" else \
            value == getattr(Config().rig, key), key


def _elevation(pitch: float, roll: float) -> float:
    """Degrees above the horizon of the optical axis of a camera pitched (nose down positive)
    and rolled about the robot's axes: SciPy's rotation of the level camera's forward axis."""
    forward = Rotation.from_euler("ZYX", [0.0, pitch, roll], degrees=True).apply([1, 0, 0])
    return float(np.degrees(np.arcsin(forward[2])))


@pytest.mark.parametrize("pitch, roll", [(-80, 0), (-45, 0), (-40, 180), (-35, 10)])
def test_a_camera_looking_at_the_sky_is_refused_naming_rig_pitch(pitch, roll):
    """Before: rig.pitch = -80 (nose up) ran, 1.7 m of VO where the level mount gave 10.7 m,
    with only "1 local maps had no informative cell" to say why."""
    assert _elevation(pitch, roll) > 30
    with pytest.raises(ConfigError, match=rf"--source kitti D: rig.pitch = {pitch}.* points "
                       rf"the left camera {_elevation(pitch, roll):.0f} degrees above the "
                       r"horizon.*no ground is in view"):
        camera_mount(_rig(pitch=pitch, roll=roll), mount_matrix(1.65), "--source kitti D")


def test_a_camera_looking_a_little_up_is_warned_about_and_level_or_down_is_not():
    with pytest.warns(UserWarning, match=r"rig.pitch = -10 points the left camera 10 degrees "
                      r"above the horizon"):
        camera_mount(_rig(pitch=-10), mount_matrix(1.65), "x")
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for pitch, roll in [(16, 0), (90, 0), (0, 90), (30, -120)]:
            assert _elevation(pitch, roll) <= 1e-9
            camera_mount(_rig(pitch=pitch, roll=roll), mount_matrix(1.65), "x")
