"""Inputs that used to give a traceback or be accepted silently: each is now a named error."""

import numpy as np
import pytest
from synthetic import make_run

from gslam_jax import gps, slam
from gslam_jax.app.cli import main
from gslam_jax.config import Config, ConfigError, apply_overrides
from gslam_jax.gps import GpsLogError
from gslam_jax.run import RunError, load_run, save_run


@pytest.fixture(scope="module")
def run():
    return make_run(steps=20)[0]


@pytest.fixture
def run_file(tmp_path, run):
    save_run(tmp_path / "r.npz", run)
    return tmp_path / "r.npz"


@pytest.fixture
def no_work(monkeypatch):
    """Fail the test if a source is simulated or the filter starts: checks come first."""
    def boom(*args, **kwargs):
        raise AssertionError("work started before the inputs were checked")
    monkeypatch.setattr("gslam_jax.slam.run_slam", boom)
    monkeypatch.setattr("gslam_jax.datasets.sim.simulate_run", boom)


def test_config_that_is_not_utf8_names_the_file_and_line(tmp_path, run_file, capsys, no_work):
    bad = tmp_path / "latin1.toml"
    bad.write_bytes(b"[filter]\nparticles = 8  # d\xe9faut\n")
    assert main(["run", str(run_file), "--config", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert f"{bad}:2: not UTF-8 text (byte 0xe9" in capsys.readouterr().err


def test_local_maps_too_large_are_refused_before_the_source(tmp_path, capsys, no_work):
    assert main(["run", "--set", "map.resolution=0.01", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "[localmap] max_range 10 m at [map] resolution 0.01 m gives local maps of 2000 x " \
           "2000 cells" in err


def test_a_huge_margin_is_an_error_not_an_empty_map(run):
    config = apply_overrides(Config(), ["map.margin=1e300"])
    with pytest.raises(ConfigError, match=r"particle maps need .* 1\.25e301 x 1\.25e301 cells"
                       r".*\[map\] margin 1e\+300 m"):
        slam.filter_config(config, run)
    with pytest.raises(ConfigError, match=r"map extent is not finite: \[map\] margin 1e\+308"):
        slam.filter_config(apply_overrides(Config(), ["map.margin=1e308"]), run)


def test_a_huge_control_is_named_not_a_memory_problem(run):
    controls = np.array(run.controls)
    controls[5, 0] = 1e12
    with pytest.raises(RunError, match=r"field 'controls': frame 5 moves 1e\+12 m in one step"):
        slam.filter_config(Config(), run._replace(controls=controls))


def test_integer_controls_in_a_run_file_are_refused(tmp_path, run):
    fields = {k: v for k, v in run._asdict().items() if v is not None}
    fields["controls"] = np.round(np.asarray(run.controls)).astype(np.int64)
    np.savez(tmp_path / "int.npz", **fields)
    with pytest.raises(RunError, match=r"int\.npz: field 'controls': stored as integers \(int64\)"):
        load_run(tmp_path / "int.npz")


@pytest.mark.parametrize("extra, what", [
    ([], "r.npz is not simulated"),
    (["--source", "kitti", "--path", "."], "--source kitti is not simulated"),
])
def test_seed_where_nothing_is_simulated_is_refused(tmp_path, run_file, capsys, no_work, extra,
                                                    what):
    argv = ["run", "--seed", "3", "--out", str(tmp_path / "o"), *extra]
    if not extra:
        argv.insert(1, str(run_file))
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "--seed 3: " in err and what in err and "filter.seed" in err


def test_seed_is_taken_for_a_simulated_gps(tmp_path, run_file, monkeypatch):
    from gslam_jax.app import pipeline

    seen = {}

    def check_gps(gps_arg, run, seed, log=None):
        seen["seed"] = seed
        raise GpsLogError("stop here")
    monkeypatch.setattr(pipeline, "check_gps", check_gps)
    assert main(["run", str(run_file), "--gps", "sim", "--seed", "3",
                 "--out", str(tmp_path / "o")]) == 2
    assert seen == {"seed": 3}


def test_gps_latitude_beyond_utm_is_refused(tmp_path):
    path = tmp_path / "polar.csv"
    gps.write_gps_log(path, [0.0, 1.0], [89.99, 89.99], [10.0, 10.001], [1.0, 1.0])
    with pytest.raises(GpsLogError, match=r"polar.csv:2: latitude 89.99 is outside UTM's range "
                       r"\(80 S to 84 N\)"):
        gps.read_gps_log(path)
    with pytest.raises(ValueError, match="outside UTM's range"):
        gps.latlon_to_utm(np.array([-80.5]), np.array([0.0]))


def test_gps_readings_at_one_time_fail_before_the_run(tmp_path, run_file, run, capsys, no_work):
    t = np.full(5, 1.0)  # inside the run's time span, but all at one instant
    lat, lon = gps.utm_to_latlon(394000.0 + np.arange(5.0), np.full(5, 3783000.0), 11, True)
    gps.write_gps_log(tmp_path / "g.csv", t, lat, lon, np.ones(5))
    assert main(["run", str(run_file), "--gps", str(tmp_path / "g.csv"),
                 "--out", str(tmp_path / "o")]) == 2
    assert "g.csv: the 5 usable GPS readings inside the run's time span are all at one time " \
           "(1.0 s)" in capsys.readouterr().err


def test_stereo_settings_reach_the_front_end(tmp_path, capsys, monkeypatch, run_file):
    from gslam_jax.datasets import kitti

    seen = {}

    def frontend(root, params, **kwargs):
        seen["stereo"] = params.frontend.stereo
        raise RunError("stop here")
    monkeypatch.setattr(kitti, "kitti_frontend", frontend)
    (tmp_path / "sequences" / "00").mkdir(parents=True)
    assert main(["run", "--source", "kitti", "--path", str(tmp_path), "--out",
                 str(tmp_path / "o"), "--set", "stereo.num_disparities=192",
                 "--set", "stereo.stride=4"]) == 2
    assert (seen["stereo"].num_disparities, seen["stereo"].stride) == (192, 4)
    assert seen["stereo"].block == 5  # the source's own setting where none is given
    del seen["stereo"]
    assert main(["run", "--source", "kitti", "--path", str(tmp_path), "--out",
                 str(tmp_path / "o")]) == 2
    assert seen["stereo"].num_disparities == 128  # KITTI's default stays
    capsys.readouterr()
    assert main(["run", str(run_file), "--set", "stereo.num_disparities=128"]) == 2
    assert "[stereo] settings apply to stereo images" in capsys.readouterr().err
    with pytest.raises(ConfigError, match=r"\[stereo\] num_disparities must be a multiple of 16"):
        apply_overrides(Config(), ["stereo.num_disparities=100"])
