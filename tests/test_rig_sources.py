"""[rig] reaches every image source: KITTI's level 1.65 m and EuRoC's computed mount are only
defaults, their ground truth follows the mount used, and sim-stereo renders the rig it assumes.
The front-end is replaced by a stand-in that records what it is given."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import gslam_jax.datasets.euroc as euroc
import gslam_jax.datasets.kitti as kitti
import gslam_jax.datasets.sim_stereo as sim_stereo
from gslam_jax.config import Config, ConfigError, apply_overrides
from gslam_jax.datasets.mount import mount_matrix, mount_values
from gslam_jax.datasets.registry import Source, get_source
from gslam_jax.sim.render import RenderParams, camera_mounts

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
KITTI = DATA / "kitti-stereo-51"
EUROC = DATA / "euroc-v1_01-static-20"


def _recorder(module, monkeypatch) -> dict:
    seen: dict = {}

    def fake(load, n, rig, t_robot_cam, times, params, **kw):
        seen.update(mount=t_robot_cam, rig=rig, n=n, **kw)
        return SimpleNamespace(run="run", summary=SimpleNamespace(text=lambda: ""),
                               poses=np.tile(np.eye(4), (n, 1, 1)))

    monkeypatch.setattr(module, "run_frontend", fake)
    return seen


def _yaw(t: np.ndarray) -> float:
    return float(np.arctan2(t[1, 0], t[0, 0]))


@pytest.mark.skipif(not KITTI.is_dir(), reason=f"real KITTI frames not found at {KITTI}")
def test_kitti_takes_the_rig_and_its_ground_truth_and_frame_follow(monkeypatch):
    seen = _recorder(kitti, monkeypatch)
    src = Source(source="kitti", path=KITTI, max_frames=5)
    loaded = get_source("kitti").load(src, Config(), None)
    level = np.eye(4)
    level[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]
    level[2, 3] = 1.65
    assert np.array_equal(seen["mount"], level)  # the default, written out by hand
    config = apply_overrides(Config(), ["rig.height=1.4", "rig.pitch=3", "rig.lateral=0.2"])
    loaded = get_source("kitti").load(src, config, None)
    mount = mount_matrix(1.4, 3.0, lateral=0.2)
    assert np.allclose(seen["mount"], mount)
    assert np.allclose(loaded.kitti_frame.t_robot_cam, mount)  # trajectory_kitti.txt's mount
    cams = kitti.read_kitti_poses(KITTI / "poses" / "seq1.txt")[:5]
    robot = [mount @ np.linalg.inv(cams[0]) @ c @ np.linalg.inv(mount) for c in cams]
    expect = np.array([[p[0, 3], p[1, 3], _yaw(p)] for p in robot])
    # (KITTI's rotations are printed to 6 digits: inverse and transpose differ by ~1e-9)
    assert np.allclose(seen["ground_truth"], expect, atol=1e-6)


@pytest.mark.skipif(not (EUROC / "mav0").is_dir(), reason=f"EuRoC frames not found at {EUROC}")
def test_euroc_mount_is_its_default_and_rig_replaces_it(monkeypatch):
    seen = _recorder(euroc, monkeypatch)
    src = Source(source="euroc", path=EUROC, max_frames=4)
    get_source("euroc").load(src, Config(), None)
    default, gt_default = seen["mount"], seen["ground_truth"]
    euroc.euroc_frontend(EUROC, euroc.EurocParams(max_frames=4))  # no mount function at all
    assert np.array_equal(seen["mount"], default)
    mav = EUROC / "mav0"
    cam0 = euroc.read_sensor_yaml(mav / "cam0" / "sensor.yaml")
    rig = euroc.euroc_rig(cam0, euroc.read_sensor_yaml(mav / "cam1" / "sensor.yaml"))
    raw_default = default @ np.linalg.inv(np.block([[rig.r_left.T, np.zeros((3, 1))],
                                                    [np.zeros((1, 3)), np.ones((1, 1))]]))
    # [rig] height replaces only the raw camera's height
    get_source("euroc").load(src, apply_overrides(Config(), ["rig.height=0.7"]), None)
    raw = seen["mount"] @ np.linalg.inv(default) @ raw_default
    assert raw[2, 3] == pytest.approx(0.7)
    assert np.allclose(raw[:3, :3], raw_default[:3, :3]) and np.allclose(raw[:2, 3],
                                                                         raw_default[:2, 3])
    # a full matrix: the rectified camera's mount is it with the rectifying rotation, and the
    # ground truth is the body's through the robot frame that mount defines
    m = mount_matrix(0.9, 20.0, 0.0, 10.0)
    get_source("euroc").load(src, apply_overrides(Config(), [f"rig.matrix={m.tolist()}"]), None)
    assert np.allclose(seen["mount"][:3, :3] @ rig.r_left, m[:3, :3])
    assert np.allclose(seen["mount"][:3, 3], m[:3, 3])
    body = euroc._ground_truth(mav / "state_groundtruth_estimate0" / "data.csv",
                               euroc._frames(mav / "cam0")[0][:4])
    robot = [b @ cam0.t_bs @ np.linalg.inv(m) for b in body]
    expect = np.array([[p[0, 3], p[1, 3], _yaw(p)] for p in robot])
    assert np.allclose(seen["ground_truth"], expect, atol=1e-9)
    assert not np.allclose(expect, gt_default, atol=1e-3)


def test_sim_stereo_renders_the_rig_it_assumes(monkeypatch):
    seen = {}

    def fake(course, seed, lm, max_frames=None, progress=None, params=None):
        seen["params"] = params
        raise RuntimeError("stop")

    monkeypatch.setattr(sim_stereo, "load_sim_stereo", fake)
    config = apply_overrides(Config(), ["rig.height=1.3", "rig.pitch=22"])
    with pytest.raises(RuntimeError, match="stop"):
        get_source("sim-stereo").load(Source(source="sim-stereo"), config, None)
    render = seen["params"].render
    assert render.camera_height == pytest.approx(1.3)
    assert render.camera_pitch == pytest.approx(np.deg2rad(22.0))
    assert render.camera_yaw == RenderParams().camera_yaw
    values = mount_values(camera_mounts(render)[0][0])  # what the front-end is given
    assert (values["height"], values["pitch"]) == pytest.approx((1.3, 22.0))
    assert sim_stereo.rig_render_params(Config(), RenderParams()) == RenderParams()
    for key in ("roll=2", "yaw=5", "forward=0.1", "lateral=0.1",
                f"matrix={np.eye(4).tolist()}"):
        with pytest.raises(ConfigError, match=rf"\[rig\] {key.split('=')[0]}: the renderer"):
            sim_stereo.rig_render_params(apply_overrides(Config(), [f"rig.{key}"]),
                                         RenderParams())
