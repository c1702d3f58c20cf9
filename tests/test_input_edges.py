"""Inputs that used to give a traceback or be accepted silently: each is now a named error."""

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from cached_runs import RUN_SETTINGS, shared_run
from synthetic import make_run

from gslam_jax import gps
from gslam_jax.app.cli import main
from gslam_jax.config import Config, ConfigError, apply_overrides
from gslam_jax.driver import sizing
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
    monkeypatch.setattr("gslam_jax.driver.slam.run_slam", boom)
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
        sizing.filter_config(config, run)
    with pytest.raises(ConfigError, match=r"map extent is not finite: \[map\] margin 1e\+308"):
        sizing.filter_config(apply_overrides(Config(), ["map.margin=1e308"]), run)


def test_a_huge_control_is_named_not_a_memory_problem(run):
    controls = np.array(run.controls)
    controls[5, 0] = 1e12
    with pytest.raises(RunError, match=r"field 'controls': frame 5 moves 1e\+12 m in one step"):
        sizing.filter_config(Config(), run._replace(controls=controls))


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
                 "--set", "stereo.stride=4", "--set", "stereo.max_depth_error=0.5",
                 "--set", "stereo.edge_ratio=0.3"]) == 2
    assert (seen["stereo"].num_disparities, seen["stereo"].stride) == (192, 4)
    assert (seen["stereo"].max_depth_error, seen["stereo"].disparity_std) == (0.5, 0.25)
    assert seen["stereo"].edge_ratio == 0.3
    assert seen["stereo"].block == 5  # the source's own setting where none is given
    del seen["stereo"]
    assert main(["run", "--source", "kitti", "--path", str(tmp_path), "--out",
                 str(tmp_path / "o")]) == 2
    # KITTI's default stays: the range from the calibration, 128 for KITTI's 380 px m
    from gslam_jax.vo.calib import RectifiedRig
    from gslam_jax.vo.stereo import with_calibrated_range
    kitti_rig = RectifiedRig.from_projections(
        np.array([707.0912, 0, 601.8873, 0, 0, 707.0912, 183.1104, 0, 0, 0, 1, 0]),
        np.array([707.0912, 0, 601.8873, -379.8145, 0, 707.0912, 183.1104, 0, 0, 0, 1, 0]),
        (1226, 370), "calib.txt")
    assert seen["stereo"].num_disparities == 0
    assert with_calibrated_range(seen["stereo"], kitti_rig).num_disparities == 128
    assert seen["stereo"].edge_ratio == 0.5  # and the front-end's
    capsys.readouterr()
    assert main(["run", str(run_file), "--set", "stereo.num_disparities=128"]) == 2
    assert "[stereo] num_disparities: settings apply to stereo images" in capsys.readouterr().err
    with pytest.raises(ConfigError, match=r"\[stereo\] num_disparities must be a multiple of 16"):
        apply_overrides(Config(), ["stereo.num_disparities=100"])
    with pytest.raises(ConfigError, match=r"\[stereo\] max_depth_error must be >= 0"):
        apply_overrides(Config(), ["stereo.max_depth_error=-0.1"])


@pytest.fixture
def slow_work(monkeypatch):
    """Fail the test if bench, table1 or compare start their work: checks come first."""
    def boom(*args, **kwargs):
        raise AssertionError("work started before the arguments were checked")
    monkeypatch.setattr("gslam_jax.app.bench.time_update", boom)
    monkeypatch.setattr("gslam_jax.app.bench.time_course", boom)
    monkeypatch.setattr("gslam_jax.app.table1.run_course", boom)
    monkeypatch.setattr("gslam_jax.app.compare.default_run", boom)
    monkeypatch.setattr("gslam_jax.app.compare.run_dense", boom)
    monkeypatch.setattr("gslam_jax.tuning.motion_fit.fit_run", boom)


@pytest.fixture
def read_only_dir(tmp_path):
    """A folder where no file can be created: a chmod 555 folder, or for root (whom
    permissions do not stop) /sys where that is read-only."""
    import os
    import tempfile

    def writable(folder):
        try:
            fd, probe = tempfile.mkstemp(dir=folder)
        except OSError:
            return False
        os.close(fd)
        os.unlink(probe)
        return True

    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        if not writable(folder):
            yield folder
        elif os.path.isdir("/sys") and not writable("/sys"):
            yield Path("/sys")
        else:
            pytest.skip("no read-only folder on this machine")
    finally:
        folder.chmod(0o755)


def test_bench_map_smaller_than_the_window_is_refused_first(capsys, slow_work):
    assert main(["bench", "--local", "128", "--map", "64"]) == 2
    err = capsys.readouterr().err
    assert "gslam: error: --map 64: smaller than the update window of --local 128 (" in err
    assert "use --map " in err
    assert main(["bench", "--local", "16", "--map", "100"]) == 2
    assert "--map 100: must be a multiple of 8 cells" in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["bench", "--particle-block", "-1"],
     "argument --particle-block: expected an integer >= 0 (0: automatic), got -1"),
    (["compare", "--store", "shared", "--pool-tiles", "-1"],
     "argument --pool-tiles: expected an integer >= 0 (0: automatic), got -1"),
])
def test_negative_block_and_pool_are_usage_errors(argv, message, capsys, slow_work):
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2
    assert message in capsys.readouterr().err


def test_bench_and_compare_check_counts_as_functions_too(slow_work):
    from gslam_jax.app import bench, compare

    with pytest.raises(bench.BenchError, match=r"--particle-block -2: must be >= 0"):
        bench.main(particles=[8], local=[16], map_side=[64], particle_block=[-2])
    with pytest.raises(compare.CompareError, match=r"--pool-tiles -1: must be >= 0"):
        compare.compare(pool_tiles=-1)


@pytest.mark.parametrize("size, message", [
    ("1e300", "--tile-size 1e+300 m is 6.25e+300 cells per side at resolution 0.16 m, more "
              "than 4096; use at most 655.36 m"),
    ("1e-9", "--tile-size 1e-09 m is under one cell at resolution 0.16 m; use 0.16 m (1 cell)"),
    ("0.25", "--tile-size 0.25 m is 1.562 cells at resolution 0.16 m, not a whole number of "
             "cells; use e.g. 0.16 m (1 cells) or 0.32 m (2 cells)"),
])
def test_compare_tile_size_is_checked_before_the_run(size, message, capsys, slow_work):
    assert main(["compare", "--tile-size", size]) == 2
    assert f"gslam: error: {message}" in capsys.readouterr().err


def test_compare_tile_wider_than_the_map_is_refused_before_the_filters(run_file, run, capsys,
                                                                       slow_work):
    size = f"{3000 * run.resolution:g}"
    assert main(["compare", str(run_file), "--particles", "4", "--tile-size", size]) == 2
    assert f"--tile-size {size} m is 3000 cells per side, wider than the map (" in \
        capsys.readouterr().err


@pytest.mark.parametrize("argv", [["bench", "--particles", "8"], ["table1", "--quick"]])
def test_json_that_is_a_folder_is_refused_first(argv, tmp_path, capsys, slow_work):
    assert main([*argv, "--json", str(tmp_path)]) == 2
    assert f"gslam: error: --json {tmp_path}: is a directory; give a file name" in \
        capsys.readouterr().err


def test_bench_plot_into_a_read_only_place_is_refused_first(read_only_dir, capsys, slow_work):
    plot = read_only_dir / "bench.png"
    assert main(["bench", "--particles", "8", "--plot", str(plot)]) == 2
    err = capsys.readouterr().err
    assert f"gslam: error: --plot {plot}: cannot write in {read_only_dir} (" in err
    assert "nothing was run" in err


def test_table1_gets_the_checks_of_run(tmp_path, capsys, slow_work):
    config = tmp_path / "fine.toml"
    config.write_text("[map]\nresolution = 1e-9\n")
    assert main(["table1", "--quick", "--config", str(config)]) == 2
    err = capsys.readouterr().err
    assert f"gslam: error: {config}: course mars-yard-a: [localmap] max_range 10 m at [map] " \
           "resolution 1e-09 m gives local maps of" in err


def test_compare_out_is_a_staged_results_folder(tmp_path, capsys, slow_work, monkeypatch):
    from gslam_jax.app import compare

    taken = tmp_path / "taken"
    taken.write_text("a file")
    assert main(["compare", "--out", str(taken)]) == 2
    assert f"gslam: error: --out {taken}: exists and is not a directory" in \
        capsys.readouterr().err
    assert taken.read_text() == "a file"

    def fake_compare(run, config, say, **options):  # the comparison's result, no work
        cfg = SimpleNamespace(num_particles=4, unknown_cells="ignore")
        return {"agreement": {"ok": True}}, None, None, cfg
    monkeypatch.setattr(compare, "_compare", fake_compare)
    monkeypatch.setattr(compare, "_plot", lambda path, *a: path.write_text("png"))
    out = tmp_path / "cmp"
    assert main(["compare", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["COMPLETE", "compare.json",
                                                     "compare_fig4.png"]
    assert main(["compare", "--out", str(out)]) == 2
    assert "is a finished results folder" in capsys.readouterr().err
    assert main(["compare", "--out", str(out), "--overwrite"]) == 0


def test_fit_motion_out_is_checked_before_the_fit(tmp_path, run_file, read_only_dir, capsys,
                                                  slow_work):
    folder = tmp_path / "folder"
    folder.mkdir()
    assert main(["fit-motion", str(run_file), "--out", str(folder), "--overwrite"]) == 2
    assert f"gslam: error: --out {folder}: is a directory; give a file name" in \
        capsys.readouterr().err
    out = read_only_dir / "fitted.toml"
    assert main(["fit-motion", str(run_file), "--out", str(out)]) == 2
    assert f"gslam: error: --out {out}: cannot write in {read_only_dir} (" in \
        capsys.readouterr().err


def test_fit_motion_on_a_full_disk_leaves_no_file(tmp_path, run_file, capsys, monkeypatch):
    import errno

    from gslam_jax.app import outfile
    from gslam_jax.tuning import motion_fit

    fit = motion_fit.MotionFit(0.05, 0.01, 0.02, 0.01, 10, 1, 0.01, 0.01, 0.001, 0.2, 0.01, False)
    monkeypatch.setattr(motion_fit, "fit_run", lambda run, window: fit)

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(outfile.os, "fsync", full)
    out = tmp_path / "fitted.toml"
    assert main(["fit-motion", str(run_file), "--out", str(out)]) == 2
    assert f"gslam: error: --out {out}: cannot write it (No space left on device); nothing " \
           "was written there" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.npz"]
    monkeypatch.undo()
    monkeypatch.setattr(motion_fit, "fit_run", lambda run, window: fit)
    assert main(["fit-motion", str(run_file), "--out", str(out)]) == 0
    assert "alpha_d = 0.05" in out.read_text()


def test_an_empty_config_file_is_an_error(tmp_path, run_file, capsys, no_work):
    empty = tmp_path / "empty.toml"
    empty.write_text("\n")
    assert main(["run", str(run_file), "--config", str(empty), "--out", str(tmp_path / "o")]) == 2
    assert f"gslam: error: {empty}: the config file is empty" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.parametrize("used, expected", [(0, "no frame uses any of the Run's"),
                                            (1, "only 1 of the Run's")])
def test_local_maps_no_frame_uses_are_counted_and_warned(tmp_path, capsys, used, expected):
    import json

    run = shared_run()  # and the other files' filter setting: their compiled filter is reused
    index = np.asarray(run.obs_index).copy()
    keep = index == index[index >= 0][0] if used else np.zeros_like(index, bool)
    path = tmp_path / "r.npz"
    save_run(path, run._replace(obs_index=np.where(keep, index, -1)))
    out = tmp_path / "o"
    assert main(["run", str(path), "--out", str(out), *RUN_SETTINGS]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["local_maps"] == run.num_local_maps and summary["local_maps_used"] == used
    stdout = capsys.readouterr().out
    assert f"WARNING: {expected} {run.num_local_maps} local maps" in stdout


def test_course_beside_a_run_file_is_refused(run_file, capsys, no_work):
    assert main(["run", str(run_file), "--course", "maze"]) == 2
    assert "a Run file is used as it is; --course" in capsys.readouterr().err


def test_a_parameter_named_twice_is_refused(run):
    from gslam_jax.tuning.gradient import TuneError, tune

    with pytest.raises(TuneError, match="parameters named twice: alpha_d"):
        tune(run, Config(), names=["alpha_d", "alpha_d"], steps=1)


def test_a_grid_smaller_than_n_says_so():
    from gslam_jax.tuning.designs import DesignNotice, design_points
    from gslam_jax.tuning.space import parse_space

    space = parse_space({"alpha_d": [0.01, 0.1], "alpha_theta": [0.01, 0.1]})
    with pytest.warns(DesignNotice, match="gives 1 set, not the 3 asked for"):
        assert design_points(space, "grid", 3).shape == (1, 2)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert design_points(space, "grid", 4).shape == (4, 2)  # 2 per axis: no notice
