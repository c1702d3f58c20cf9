"""The command line's input checks: GPS logs, source options, partial ground truth, progress."""

import io
import json

import numpy as np
import pytest
from cached_runs import FRAMES, RUN_SETTINGS, run_file, shared_run

from gslam_jax import gps
from gslam_jax.app.cli import ProgressBar, main
from gslam_jax.run import RunError

SITE = np.array([394000.0, 3783000.0])  # UTM zone 11N, like the simulated receiver's site
# Every `gslam run` here uses cached_runs.RUN_SETTINGS (filter.resample_ratio = 0.3, which
# test_ess_plot_threshold_is_the_resample_ratio looks for): the filter compiles once.


def _strict_json(path):
    """Parse JSON, refusing NaN / Infinity (Python's json accepts them by default)."""
    def bad(name):
        raise ValueError(f"{path}: invalid JSON constant {name}")
    return json.loads(path.read_text(), parse_constant=bad)


def _run_file(tmp_path, **changes):
    """The shared Run of ``FRAMES`` frames (``cached_runs``), with ``changes``, in r.npz."""
    return run_file(tmp_path / "r.npz", **changes)


def _gps_log(path, run, times):
    """A GPS log of the run's true positions at ``times`` (run clock), EPE 1 m."""
    gt = np.asarray(run.ground_truth)
    t = np.asarray(run.timestamps)
    xy = np.stack([np.interp(times, t, gt[:, k]) for k in range(2)], -1) + SITE
    lat, lon = gps.utm_to_latlon(xy[:, 0], xy[:, 1], 11, True)
    gps.write_gps_log(path, times, lat, lon, np.ones(len(times)))
    return path


@pytest.fixture
def no_filter(monkeypatch):
    """Fail the test if the filter starts: the checks must come first."""
    def boom(*args, **kwargs):
        raise AssertionError("the filter ran before the inputs were checked")
    monkeypatch.setattr("gslam_jax.driver.slam.run_slam", boom)


def test_gps_log_is_checked_before_the_filter(tmp_path, capsys, no_filter):
    run, path = _run_file(tmp_path)
    out = tmp_path / "out"
    assert main(["run", str(path), "--gps", str(tmp_path / "missing.csv"), "--out", str(out)]) == 2
    assert "missing.csv: cannot read GPS log" in capsys.readouterr().err
    assert not out.exists()  # created up front, removed again as nothing was written
    late = _gps_log(tmp_path / "late.csv", run, np.arange(100.0, 120.0))  # not on the run's clock
    assert main(["run", str(path), "--gps", str(late), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "late.csv: 0 of 20 GPS readings fall inside the run's time span" in err
    assert "seconds on the run's clock" in err
    run_file(tmp_path / "no_truth.npz", ground_truth=None)
    assert main(["run", str(tmp_path / "no_truth.npz"), "--gps", "sim", "--out", str(out)]) == 2
    assert "--gps sim needs a run with ground truth" in capsys.readouterr().err


def test_out_that_is_a_file_fails_up_front(tmp_path, capsys, no_filter):
    _, path = _run_file(tmp_path)
    taken = tmp_path / "taken"
    taken.write_text("not a directory")
    assert main(["run", str(path), "--out", str(taken)]) == 2
    assert f"--out {taken}: exists and is not a directory" in capsys.readouterr().err
    assert taken.read_text() == "not a directory"


@pytest.mark.slow
def test_gps_report_counts_the_readings_used_and_warns(tmp_path, capsys):
    run, path = _run_file(tmp_path)
    # 10 readings during the run (0-4.8 s), 15 after it: fewer than half can be used.
    times = np.r_[np.arange(10) * 0.5, 10.0 + np.arange(15)]
    log = _gps_log(tmp_path / "gps.csv", run, times)
    out = tmp_path / "out"
    assert main(["run", str(path), *RUN_SETTINGS, "--gps", str(log), "--out", str(out)]) == 0
    stdout = capsys.readouterr().out
    assert "WARNING" in stdout and "only 10 of 25 GPS readings fall inside" in stdout
    assert "GPS: 10 of 25 readings used (15 outside the run's time span)" in stdout
    report = _strict_json(out / "summary.json")["gps"]
    assert (report["readings"], report["inside_run"], report["used"]) == (25, 10, 10)
    assert 0.0 <= report["weighted_residual"] < 1e3
    assert 0.0 <= report["residual_rms_m"] < 5.0
    assert (out / "trajectory_utm.txt").exists()


@pytest.fixture(scope="module")
def partial_truth_run(tmp_path_factory):
    """One `gslam run` on the shared Run with frames 5-9 of its ground truth unknown and
    filter.resample_ratio = 0.3 (not the default 0.5), recording the threshold each ESS plot
    was drawn with. Returns (results folder, stdout, thresholds); the tests below check
    different parts of it."""
    import contextlib

    from gslam_jax.app import plots

    tmp = tmp_path_factory.mktemp("partial_truth")
    gt = np.array(shared_run().ground_truth, np.float64)
    gt[5:10] = np.nan
    _, path = _run_file(tmp, ground_truth=gt)
    thresholds = []
    save_ess_png = plots.save_ess_png

    def spy(*args, **kwargs):
        thresholds.append(kwargs.get("threshold", "default"))
        return save_ess_png(*args, **kwargs)
    stdout = io.StringIO()
    with pytest.MonkeyPatch.context() as patch, contextlib.redirect_stdout(stdout):
        patch.setattr(plots, "save_ess_png", spy)
        assert main(["run", str(path), *RUN_SETTINGS, "--out", str(tmp / "out")]) == 0
    return tmp / "out", stdout.getvalue(), thresholds


@pytest.mark.slow
def test_partial_ground_truth_is_scored_over_its_finite_frames(partial_truth_run):
    out, stdout, _ = partial_truth_run
    summary = _strict_json(out / "summary.json")
    assert summary["gt_frames_scored"] == FRAMES - 5
    for key in ("vo_rms_m", "slam_rms_m", "vo_final_error_m", "slam_final_error_m"):
        assert np.isfinite(summary[key]) and summary[key] >= 0, key
    assert "VO-only RMS: nan" not in stdout
    assert f"(over the {FRAMES - 5} of {FRAMES} frames with ground truth)" in stdout


@pytest.mark.slow
def test_ess_plot_threshold_is_the_resample_ratio(partial_truth_run):
    out, _, thresholds = partial_truth_run
    assert thresholds == [0.3]
    assert (out / "ess.png").exists()


def test_progress_bar_is_one_final_line_when_not_a_terminal():
    stream = io.StringIO()
    bar = ProgressBar("work", stream=stream)
    for done in range(11):
        bar(done, 10)
    bar(10, 10)
    text = stream.getvalue()
    assert "\r" not in text and text.count("\n") == 1 and text.startswith("work: 10/10")

    class Terminal(io.StringIO):
        def isatty(self):
            return True
    tty = Terminal()
    ProgressBar("work", stream=tty)(10, 10)
    assert tty.getvalue().startswith("\rwork [")


def test_max_frames_must_be_a_positive_integer(capsys, monkeypatch):
    def boom(*args, **kwargs):
        raise AssertionError("the source ran with a bad --max-frames")
    monkeypatch.setattr("gslam_jax.datasets.sim.simulate_run", boom)
    for bad in ("0", "-3", "2.5"):
        with pytest.raises(SystemExit) as exit_:
            main(["run", "--max-frames", bad])
        assert exit_.value.code == 2
        assert "--max-frames: expected a positive integer" in capsys.readouterr().err


@pytest.mark.parametrize("extra, name", [(["--max-frames", "5"], "--max-frames"),
                                         (["--path", "data"], "--path"),
                                         (["--sequence", "00"], "--sequence"),
                                         (["--source", "kitti"], "--source")])
def test_run_file_rejects_source_options(tmp_path, capsys, no_filter, extra, name):
    _, path = _run_file(tmp_path)
    assert main(["run", str(path), *extra, "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert f"{path}: a Run file is used as it is; {name}" in err


def test_source_options_for_another_source_are_rejected(tmp_path, capsys):
    assert main(["run", "--sequence", "00", "--out", str(tmp_path / "out")]) == 2
    assert "--sequence is for --source kitti, not --source sim" in capsys.readouterr().err
    assert main(["run", "--source", "euroc", "--path", str(tmp_path), "--sequence", "00",
                 "--out", str(tmp_path / "out")]) == 2
    assert "--sequence is for --source kitti, not --source euroc" in capsys.readouterr().err


def test_kitti_and_euroc_get_sequence_and_max_frames(tmp_path, capsys, monkeypatch):
    from gslam_jax.datasets import euroc, kitti

    seen = {}

    def fake(name):
        def frontend(root, params, **kwargs):
            seen[name] = params
            raise RunError(f"{root}: stop here")
        return frontend
    monkeypatch.setattr(kitti, "kitti_frontend", fake("kitti"))
    monkeypatch.setattr(euroc, "euroc_frontend", fake("euroc"))
    for seq in ("00", "05"):
        (tmp_path / "sequences" / seq).mkdir(parents=True)
    out = str(tmp_path / "out")
    assert main(["run", "--source", "kitti", "--path", str(tmp_path), "--sequence", "05",
                 "--max-frames", "7", "--out", out]) == 2
    assert (seen["kitti"].sequence, seen["kitti"].max_frames) == ("05", 7)
    assert main(["run", "--source", "euroc", "--path", str(tmp_path), "--max-frames", "9",
                 "--out", out]) == 2
    assert seen["euroc"].max_frames == 9
    del seen["kitti"]
    assert main(["run", "--source", "kitti", "--path", str(tmp_path), "--out", out]) == 2
    err = capsys.readouterr().err
    assert "holds sequences 00, 05; choose one (--sequence NN" in err
    assert "kitti" not in seen


def test_table1_particles_default_to_the_config(tmp_path, monkeypatch, capsys):
    from gslam_jax.app import table1

    used = []

    def fake_course(course, seed, config, progress=None):
        used.append((course, config.filter.particles))
        return {"course": course, "seed": seed, "distance_m": 1.0, "vo_rms_m": 1.0,
                "slam_rms_m": 0.5, "filter_seconds": 0.0}
    monkeypatch.setattr(table1, "run_course", fake_course)
    cfg = tmp_path / "t.toml"
    cfg.write_text("[filter]\nparticles = 50\n[course.maze.filter]\nparticles = 40\n")
    base = ["table1", "--courses", "mars-yard-a", "maze", "--seeds", "0"]
    assert main([*base, "--config", str(cfg), "--json", str(tmp_path / "t.json")]) == 0
    assert used == [("mars-yard-a", 50), ("maze", 40)]
    assert json.loads((tmp_path / "t.json").read_text())["particles"] == [40, 50]
    used.clear()
    assert main([*base, "--config", str(cfg), "--particles", "30"]) == 0
    assert used == [("mars-yard-a", 30), ("maze", 30)]
    used.clear()
    assert main(base) == 0
    assert used == [("mars-yard-a", 200), ("maze", 200)]


def test_table1_set_overrides_every_course_after_its_course_tables(tmp_path, monkeypatch,
                                                                   capsys):
    from gslam_jax.app import table1

    used = []

    def fake_course(course, seed, config, progress=None):
        used.append((course, config.filter.proposal, config.filter.beta_prev,
                     config.filter.proposal_cell_stride))
        return {"course": course, "seed": seed, "distance_m": 1.0, "vo_rms_m": 1.0,
                "slam_rms_m": 0.5, "filter_seconds": 0.0}
    monkeypatch.setattr(table1, "run_course", fake_course)
    cfg = tmp_path / "t.toml"
    cfg.write_text("[course.maze.filter]\nbeta_prev = 0.2\nproposal_cell_stride = 2\n")
    argv = ["table1", "--courses", "mars-yard-a", "maze", "--seeds", "0", "--config", str(cfg),
            "--set", "filter.proposal=informed", "--set", "filter.proposal_cell_stride=8"]
    assert main(argv) == 0
    assert used == [("mars-yard-a", "informed", 0.05, 8), ("maze", "informed", 0.2, 8)]
    assert main([*argv[:-1], "filter.proposal_cell_stride=0"]) == 2
    assert "proposal_cell_stride" in capsys.readouterr().err


def test_compare_accepts_a_table1_config(tmp_path, monkeypatch, capsys):
    from gslam_jax.app import compare as compare_module

    seen = {}

    def fake_compare(run, config, **kwargs):
        seen["config"] = config
        return {}
    monkeypatch.setattr(compare_module, "compare", fake_compare)
    cfg = tmp_path / "t.toml"
    cfg.write_text("[localmap]\ntravel = 1.0\n[course.maze.filter]\nbeta_prev = 0.2\n")
    assert main(["compare", "--config", str(cfg)]) == 0
    assert seen["config"].localmap.travel == 1.0 and seen["config"].filter.beta_prev == 0.05
    assert "[course.<name>.*] tables (maze) are not applied" in capsys.readouterr().out



def test_trajectory_errors_match_the_metrics_on_full_ground_truth():
    from gslam_jax.evaluation import metrics
    from gslam_jax.evaluation.metrics import errors_over_known_frames

    run = shared_run()
    gt, vo = np.asarray(run.ground_truth), run.vo_poses()
    slam = gt + 0.01 * np.random.default_rng(0).standard_normal(gt.shape)
    got = errors_over_known_frames({"vo": vo, "slam": slam}, gt)
    assert got == {"gt_frames_scored": FRAMES,
                   "vo_rms_m": metrics.rms_after_fit(vo, gt),
                   "vo_final_error_m": metrics.final_position_error(vo, gt),
                   "slam_rms_m": metrics.rms_after_fit(slam, gt),
                   "slam_final_error_m": metrics.final_position_error(slam, gt)}
    no_heading = gt.copy()
    no_heading[:, 2] = np.nan  # positions only: RMS, but no start-anchored final error
    got = errors_over_known_frames({"vo": vo, "slam": slam}, no_heading)
    assert got["vo_rms_m"] == metrics.rms_after_fit(vo, gt) and "vo_final_error_m" not in got


@pytest.mark.parametrize("argv, message", [
    (["run", "--seed", "-1"], "argument --seed: a seed must be in [0, 2^32), got -1"),
    (["run", "--seed", str(2 ** 32)], "a seed must be in [0, 2^32)"),
    (["bench", "--particles", "0"], "argument --particles: expected a positive integer, got 0"),
    (["search", "--n", "0"], "argument --n: expected a positive integer, got 0"),
    (["compare", "--particles", "-5"], "argument --particles: expected a positive integer"),
    (["compare", "--tile-size", "-1"], "argument --tile-size: expected a finite positive number"),
    (["tune", "--lr", "nan"], "argument --lr: expected a finite positive number, got nan"),
    (["tune", "--lr", "-1"], "argument --lr: expected a finite positive number, got -1"),
    (["tune", "--lr", "inf"], "argument --lr: expected a finite positive number, got inf"),
])
def test_counts_and_seeds_are_usage_errors(argv, message, capsys):
    """Seeds and counts are checked by argparse, before any work (they were tracebacks from
    NumPy's RNG or the filter's config, or, for search --n 0, silently the space file's n)."""
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2
    assert message in capsys.readouterr().err


def test_course_path_is_the_sim_path_source(tmp_path, capsys, monkeypatch):
    """--course-path FILE reads FILE through --source sim-path; beside a Run file, another
    --source or a --path it is refused before anything loads."""
    from gslam_jax.datasets import sim_path
    from gslam_jax.errors import DatasetError

    seen = []

    def fake(path, **kwargs):
        seen.append((path, kwargs["course"]))
        raise DatasetError(f"{path}: stop here")
    monkeypatch.setattr(sim_path, "simulate_path", fake)
    poses = tmp_path / "loop.txt"
    poses.write_text("0 0 0 0 0 0 0 1\n")
    out = str(tmp_path / "out")
    for extra in ([], ["--source", "sim-path"]):
        assert main(["run", "--course-path", str(poses), "--course", "arroyo-a", *extra,
                     "--out", out]) == 2
        assert f"{poses}: stop here" in capsys.readouterr().err
    assert seen == [(poses, "arroyo-a")] * 2
    _, run_file = _run_file(tmp_path)
    for extra, message in [
            ([str(run_file)], f"{run_file}: a Run file is used as it is; --course-path {poses}"),
            (["--source", "sim"], f"--course-path {poses} is --source sim-path --path FILE; it "
             "cannot be used with --source sim"),
            (["--source", "kitti"], "cannot be used with --source kitti"),
            (["--path", str(tmp_path / "other.txt")], f"--course-path {poses} and --path "
             f"{tmp_path / 'other.txt'}: --course-path {poses} is --source sim-path --path "
             "FILE; name the trajectory once")]:
        assert main(["run", "--course-path", str(poses), *extra, "--out", out]) == 2
        assert message in capsys.readouterr().err
    assert len(seen) == 2


def _procrustes(b: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R (proper) and shift l minimising sum |R b_i + l - a_i|^2 (equal weights)."""
    mb, ma = b.mean(0), a.mean(0)
    u, _, vt = np.linalg.svd((a - ma).T @ (b - mb))
    d = np.diag([1.0, np.sign(np.linalg.det(u @ vt))])
    rot = u @ d @ vt
    return rot, ma - rot @ mb


def test_a_gps_reading_far_beyond_its_epe_is_dropped_and_named(tmp_path, capsys):
    """One reading of a 1 m EPE log moved 1.1 km: the alignment leaves it out, names its line
    and time in a warning and in summary.json, and the UTM path is the fit to the other
    readings (an independent Procrustes fit of trajectory_tum.txt here)."""
    run, path = _run_file(tmp_path)
    times = np.arange(10) * 0.5
    gt = np.asarray(run.ground_truth)
    t = np.asarray(run.timestamps)
    xy = np.stack([np.interp(times, t, gt[:, k]) for k in range(2)], -1) + SITE
    xy[4, 0] += 1100.0
    lat, lon = gps.utm_to_latlon(xy[:, 0], xy[:, 1], 11, True)
    log = tmp_path / "gps.csv"
    gps.write_gps_log(log, times, lat, lon, np.ones(len(times)))
    out = tmp_path / "out"
    assert main(["run", str(path), *RUN_SETTINGS, "--gps", str(log), "--out", str(out)]) == 0
    stdout = capsys.readouterr().out
    assert "1 GPS reading(s) lie far beyond their EPE" in stdout
    assert "line 6, time 2.000 s, 110" in stdout, stdout
    report = _strict_json(out / "summary.json")["gps"]
    assert report["used"] == 9 and [o["line"] for o in report["outliers"]] == [6]
    assert report["outliers"][0]["residual_m"] > 1000 and report["residual_rms_m"] < 5.0
    est = np.loadtxt(out / "trajectory_tum.txt")
    at = np.stack([np.interp(times, est[:, 0], est[:, k]) for k in (1, 2)], -1)
    clean = np.arange(10) != 4
    rot, shift = _procrustes(at[clean], xy[clean] - SITE)
    want = est[:, 1:3] @ rot.T + shift + SITE
    utm = np.loadtxt(out / "trajectory_utm.txt")
    np.testing.assert_allclose(utm[:, 1:3], want, atol=5e-3)


def test_outlier_test_keeps_a_drifting_path_and_three_readings():
    from gslam_jax.gps.georeference import outlier

    epe = np.ones(8)
    used = np.ones(8, bool)
    assert outlier(np.array([0.5, 0.4, 0.6, 0.5, 9.0, 0.5, 0.3, 0.4]), epe, used) == 4
    # every residual wide (a drifting path): 9 m is under 5 times the typical 4 m
    assert outlier(np.array([4.0, 3.5, 4.5, 4.0, 9.0, 4.2, 3.8, 4.1]), epe, used) is None
    assert outlier(np.array([0.5, 0.4, 60.0, 0.0, 0, 0, 0, 0]), epe, used & (np.arange(8) < 3)) \
        is None


def test_start_takes_a_negative_value_without_an_equals_sign(tmp_path, capsys):
    """Before: ``--start -5,0,0`` was a usage error ("expected one argument"): argparse took
    the value for an option; ``--start=-5,0,0`` was needed."""
    from gslam_jax.app.arguments import attach_negative_values

    assert main(["run", "--start", "-5,0,0", "--out", str(tmp_path / "o")]) == 2
    assert "--start and --start-sigma place the run in a prior map" in capsys.readouterr().err
    assert attach_negative_values(["run", "--start", "-5.5,-1,0.2", "--set", "a.b=-1"]) == \
        ["run", "--start=-5.5,-1,0.2", "--set", "a.b=-1"]
    assert attach_negative_values(["run", "--start", "--out", "x"]) == \
        ["run", "--start", "--out", "x"]  # a missing value stays argparse's error
    assert list(tmp_path.iterdir()) == []
