"""``gslam run`` as functions (app/pipeline.py): one preparation step for every command, and a
complete results folder whose files hold what the driver computed."""

from __future__ import annotations

import json

import numpy as np
import pytest
from synthetic import make_run

from gslam_jax.app import pipeline
from gslam_jax.config import Config, ConfigError, apply_overrides
from gslam_jax.datasets.registry import Source
from gslam_jax.driver import slam
from gslam_jax.io import read_tum
from gslam_jax.run import save_run


def _same_poses(a: np.ndarray, b: np.ndarray) -> None:
    """Equal (x, y) and headings equal modulo 2 pi (TUM files hold quaternions)."""
    np.testing.assert_allclose(a[:, :2], b[:, :2], atol=1e-6)
    np.testing.assert_allclose(np.angle(np.exp(1j * (a[:, 2] - b[:, 2]))), 0.0, atol=1e-6)


@pytest.fixture(scope="module")
def run():
    return make_run(steps=24)[0]


@pytest.fixture
def config():
    return apply_overrides(Config(), ["filter.particles=16", "localmap.max_range=5.0",
                                      "localmap.travel=1.0"])


def test_prepare_source_loads_a_run_file_and_says_what_it_loaded(tmp_path, run, config, capsys):
    save_run(tmp_path / "r.npz", run)
    src = Source(run_file=tmp_path / "r.npz")
    pipeline.check_inputs(src, config)
    loaded = pipeline.prepare_source(src, config)
    np.testing.assert_array_equal(loaded.run.controls, run.controls)
    np.testing.assert_array_equal(loaded.run.local_maps, run.local_maps)
    out = capsys.readouterr().out
    assert f"source: {tmp_path / 'r.npz'}: 24 frames, {run.num_local_maps} local maps" in out


def test_check_inputs_comes_before_any_loading(tmp_path, config, monkeypatch):
    monkeypatch.setattr("gslam_jax.datasets.sim.simulate_run",
                        lambda *a, **k: pytest.fail("loaded before the checks"))
    with pytest.raises(ConfigError, match="--path is for"):
        pipeline.check_inputs(Source(source="sim", path=tmp_path), config)
    big = apply_overrides(config, ["localmap.cells=2048"])
    with pytest.raises(ConfigError, match="more than 1024 per side"):
        pipeline.check_inputs(Source(), big)


def test_run_pipeline_writes_what_the_driver_computed(tmp_path, run, config, capsys):
    save_run(tmp_path / "r.npz", run)
    folder, summary = pipeline.run_pipeline(Source(run_file=tmp_path / "r.npz"), config,
                                            tmp_path / "out")
    direct = slam.run_slam(run, config)
    times, poses = read_tum(folder / "trajectory_tum.txt")
    np.testing.assert_allclose(times, run.timestamps)
    _same_poses(poses, direct.path)
    _, vo = read_tum(folder / "vo_tum.txt")
    _same_poses(vo, run.vo_poses())
    with np.load(folder / "map.npz") as m:
        np.testing.assert_array_equal(m["k"], direct.kmap)
        np.testing.assert_array_equal(m["S"], direct.smap)
    on_disk = json.loads((folder / "summary.json").read_text())
    assert on_disk["frames"] == run.num_frames == summary["frames"]
    assert on_disk["resampling_events"] == int(np.sum(direct.resampled))
    assert on_disk["local_maps_used"] == on_disk["local_maps"] == run.num_local_maps
    assert (folder / "COMPLETE").is_file()
    assert "WARNING" not in capsys.readouterr().out
