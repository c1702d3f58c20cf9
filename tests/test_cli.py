"""The command line on a native Run file."""

import json
import subprocess
import sys

import numpy as np
import pytest
from cached_runs import FRAMES, RUN_SETTINGS, run_file

from gslam_jax.app.cli import main

# Every `gslam run` here (the tuned config's too) uses cached_runs.RUN_SETTINGS: the filter
# compiles once and the later runs reuse it.


@pytest.fixture(scope="module")
def mean_run(tmp_path_factory):
    """One `gslam run` with [filter] estimate = "mean" on the shared Run; the tests below read
    different files of its results folder."""
    tmp = tmp_path_factory.mktemp("mean_run")
    run, path = run_file(tmp / "r.npz")
    out = tmp / "out"
    assert main(["run", str(path), *RUN_SETTINGS, "--set", "filter.estimate=mean",
                 "--out", str(out)]) == 0
    return run, out


def test_help_lists_subcommands():
    out = subprocess.run([sys.executable, "-m", "gslam_jax.app.cli", "--help"],
                         capture_output=True, text=True)
    assert out.returncode == 0
    for cmd in ("run", "bench"):
        assert cmd in out.stdout


@pytest.mark.slow
def test_run_on_npz_writes_results(mean_run):
    _, out = mean_run
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == FRAMES and summary["particles"] == 8
    assert summary["gt_distance_m"] > 0 and summary["slam_drift_pct"] >= 0
    assert summary["vo_drift_pct"] >= 0
    for name in ("trajectory_tum.txt", "trajectory_robot_kitti.txt", "map.npz", "config.toml",
                 "ground_truth.png"):
        assert (out / name).exists()
    assert len((out / "trajectory_robot_kitti.txt").read_text().splitlines()) == FRAMES
    assert not (out / "trajectory_kitti.txt").exists()  # KITTI's frame: KITTI runs
    # the map checked against itself: a short drive that never comes back has nothing to check
    check = summary["map_consistency"]
    assert check["consistent"] is True and check["revisits_checked"] == 0


def _counts_at(run, poses: np.ndarray, like: dict) -> np.ndarray:
    """Point counts k of every local map of ``run`` placed at ``poses`` on the lattice of the
    map file ``like`` (the metrics' numpy placement, eq. 14's sum)."""
    from gslam_jax.gridmap import GridMap
    from gslam_jax.gridmap.pose_maps import pose_map

    shape = like["k"].shape
    lattice = GridMap(np.zeros(shape), np.zeros(shape), tuple(like["origin"]),
                      float(like["resolution"]))
    return pose_map(run, poses, lattice=lattice).k


@pytest.mark.slow
def test_map_path_is_the_path_of_the_written_map(mean_run):
    """map.npz is the final best particle's map; map_path_tum.txt is that particle's path: the
    local maps placed along it give map.npz's counts in every cell, which the reported path
    (here the weighted mean) does not."""
    from gslam_jax.io import read_tum

    run, out = mean_run
    with np.load(out / "map.npz") as m:
        written = {name: m[name] for name in m.files}
    _, map_path = read_tum(out / "map_path_tum.txt")
    _, reported = read_tum(out / "trajectory_tum.txt")
    assert map_path.shape == (FRAMES, 3)
    np.testing.assert_array_equal(_counts_at(run, map_path, written), written["k"])
    assert (_counts_at(run, reported, written) != written["k"]).any()


@pytest.mark.slow
def test_a_map_on_the_start_axes_is_written_with_its_heading(tmp_path):
    """[map] axes = "start": map.npz's lattice lies on the robot's start axes (its heading is
    the start heading), and the local maps placed along map_path_tum.txt (in the run's frame)
    on that turned lattice give its counts in every cell."""
    from gslam_jax.gridmap import load_map
    from gslam_jax.gridmap.pose_maps import pose_map
    from gslam_jax.io import read_tum

    start = np.array([0.4, -0.2, 0.9])
    run, path = run_file(tmp_path / "r.npz", initial_pose=start)
    out = tmp_path / "out"
    assert main(["run", str(path), *RUN_SETTINGS, "--set", "map.axes=start",
                 "--out", str(out)]) == 0
    grid = load_map(out)
    assert grid.heading == pytest.approx(start[2])
    _, map_path = read_tum(out / "map_path_tum.txt")
    np.testing.assert_allclose(map_path[0, :2], start[:2], atol=0.5)  # the run's frame
    np.testing.assert_array_equal(pose_map(run, map_path, lattice=grid).k, grid.k)
    assert (pose_map(run, map_path, lattice=grid._replace(heading=0.0)).k != grid.k).any()
    assert (out / "map.png").is_file()


def test_bad_inputs_exit_2_with_a_message(tmp_path, capsys):
    assert main(["run", str(tmp_path / "missing.npz")]) == 2
    assert "missing.npz: no such file" in capsys.readouterr().err
    bad = tmp_path / "bad.toml"
    bad.write_text("[filter]\nparticls = 2\n")
    run_file(tmp_path / "r.npz")
    assert main(["run", str(tmp_path / "r.npz"), "--config", str(bad)]) == 2
    assert "unknown key 'particls'" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_:  # argparse's usage error, before any JAX work
        main(["run", "--course", "mars-yard-c"])
    assert exit_.value.code == 2
    assert "invalid choice: 'mars-yard-c'" in capsys.readouterr().err


@pytest.mark.slow
def test_bench_writes_every_figure(tmp_path, capsys):
    """A tiny bench sweep: one row per combination, every figure finite and positive."""
    out = tmp_path / "bench.json"
    assert main(["bench", "--particles", "4", "8", "--local", "16", "--map", "64", "--mode",
                 "ignore", "--repeats", "1", "--particle-block", "0", "3", "--json", str(out)]) == 0
    rows = json.loads(out.read_text())["results"]
    assert [(r["particles"], r["particle_block"]) for r in rows] == [(4, 4), (4, 3), (8, 8), (8, 3)]
    for r in rows:
        for key in ("ms_per_update", "us_per_particle", "predict_us_per_particle",
                    "mb_per_particle"):
            assert r[key] > 0, (key, r)
        assert r["resample_ms"] >= 0
    assert "us/particle" in capsys.readouterr().out


def test_building_the_parser_does_not_import_jax():
    """`gslam compare --exact` sets XLA_FLAGS before JAX starts; the parser must not start it."""
    code = ("import sys; from gslam_jax.app.cli import build_parser; build_parser(); "
            "sys.exit(1 if 'jax' in sys.modules else 0)")
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_run_config_applies_the_course_section_of_a_table1_config(tmp_path):
    import argparse

    from gslam_jax.app.arguments import load_config

    path = tmp_path / "t.toml"
    path.write_text("[motion]\nalpha_d = 0.04\n[course.maze.filter]\nbeta_prev = 0.2\n")

    def ns(**kw):
        base = dict(config=path, set=["motion.alpha_theta = 0.07"], source="sim",
                    course="mars-yard-a", run_file=None)
        return argparse.Namespace(**{**base, **kw})

    maze = load_config(ns(course="maze"))
    assert (maze.filter.beta_prev, maze.motion.alpha_d, maze.motion.alpha_theta) == \
        (0.2, 0.04, 0.07)
    other = load_config(ns())
    assert (other.filter.beta_prev, other.motion.alpha_d) == (0.05, 0.04)
    from_file = load_config(ns(course="maze", run_file=tmp_path / "log.npz"))
    assert from_file.filter.beta_prev == 0.05  # a Run file is not a simulated course


@pytest.mark.slow
def test_search_prints_the_best_score_and_writes_a_config(tmp_path, capsys):
    from gslam_jax.config import load_config

    run_file(tmp_path / "r.npz")
    (tmp_path / "space.toml").write_text(
        "[space]\nalpha_d = [0.01, 0.1]\nobs_weight = [0.3, 1.0]\n")
    rc = main(["search", str(tmp_path / "r.npz"), "--space", str(tmp_path / "space.toml"),
               "--n", "4", *RUN_SETTINGS, "--out", str(tmp_path / "s")])
    assert rc == 0
    doc = json.loads((tmp_path / "s" / "results.json").read_text())
    top = doc["results"][0]
    printed = capsys.readouterr().out
    assert f"best: rms = {top['rms']:.5g} m at alpha_d = {top['alpha_d']:.5g}" in printed
    cfg = load_config(tmp_path / "s" / "best.toml")
    assert cfg.motion.alpha_d == top["alpha_d"] and cfg.map.obs_weight == top["obs_weight"]
    assert cfg.filter.particles == 8


@pytest.mark.slow
def test_tune_prints_its_loss_and_writes_a_config_that_runs(tmp_path, capsys, monkeypatch):
    from matplotlib.figure import Figure

    from gslam_jax.config import load_config

    run_file(tmp_path / "r.npz")
    rc = main(["tune", str(tmp_path / "r.npz"), "--objective", "supervised", "--steps", "2",
               "--params", "alpha_d,beta_new,min_variance", "--runs-per-step", "1",
               *RUN_SETTINGS, "--out", str(tmp_path / "t")])
    assert rc == 0
    tuned = json.loads((tmp_path / "t" / "tuned.json").read_text())
    printed = capsys.readouterr().out
    assert f"step 2/2: loss {tuned['losses'][1]:.6g}" in printed
    cfg = load_config(tmp_path / "t" / "tuned.toml")
    v = tuned["values"]
    assert (cfg.motion.alpha_d, cfg.filter.beta_new, cfg.map.min_variance) == \
        (v["alpha_d"], v["beta_new"], v["min_variance"])
    assert v["alpha_d"] != 0.05 and cfg.filter.particles == 8
    # the tuned config's run: its figures are written as empty files, not drawn (drawing is
    # most of a run's time here; test_run_on_npz_writes_results and the map-axes test draw them)
    monkeypatch.setattr(Figure, "savefig", lambda self, fname, *a, **kw: open(fname, "wb").close())
    rc = main(["run", str(tmp_path / "r.npz"), "--config", str(tmp_path / "t" / "tuned.toml"),
               "--out", str(tmp_path / "run"), "--no-map-check"])
    assert rc == 0
    assert "map_consistency" not in json.loads((tmp_path / "run" / "summary.json").read_text())
    assert (tmp_path / "run" / "config.toml").read_text() == \
        (tmp_path / "t" / "tuned.toml").read_text()


@pytest.mark.slow
def test_run_reports_the_configured_estimate(mean_run):
    """[filter] estimate = "mean": the trajectory files and the RMS are the weighted mean poses."""
    from gslam_jax.evaluation.metrics import rms_after_fit
    from gslam_jax.io import read_tum

    run, out = mean_run
    mean = np.load(out / "trace.npz")["mean_pose"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["estimate"] == "mean"
    np.testing.assert_allclose(read_tum(out / "trajectory_tum.txt")[1][:, :2], mean[:, :2],
                               atol=1e-4)
    assert summary["slam_rms_m"] == pytest.approx(rms_after_fit(mean, run.ground_truth), rel=1e-4)
