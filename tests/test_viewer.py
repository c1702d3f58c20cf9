"""The Rerun viewer, headless: ``gslam run --viewer-save`` and ``gslam view --save`` write a
recording that is read back (``rerun.chunk.RrdReader``) and checked against the results folder
the same run wrote (trace.npz, the TUM files, map.npz), not against the viewer's own code."""

from __future__ import annotations

import sys

import numpy as np
import pytest
from synthetic import make_run

from gslam_jax.app.cli import main
from gslam_jax.io import read_tum
from gslam_jax.run import save_run

rr = pytest.importorskip("rerun", reason="the viewer extra (rerun-sdk) is not installed")

FRAMES, PARTICLES, EVERY = 20, 8, 6
SETTINGS = ["--set", f"filter.particles={PARTICLES}"]


def _entities(path) -> dict[str, list[dict]]:
    """Every logged row of the recording by entity: static rows first (no 'frame'), then by
    frame; GridMap data as a uint8 array, the rest as Python values."""
    from rerun.chunk import RrdReader

    out: dict[str, list[dict]] = {}
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        names = [n for n in batch.schema.names if n not in ("rerun.controls.RowId", "log_time")]
        for i in range(batch.num_rows):
            row = {}
            for name in names:
                value = batch.column(name)[i]
                row[name] = (np.asarray(value.values[0].values) if name == "GridMap:data"
                             else value.as_py())
            out.setdefault(chunk.entity_path, []).append(row)
    for rows in out.values():
        rows.sort(key=lambda r: (r.get("frame") is not None, r.get("frame") or 0))
    return out


def _temporal(rows: list[dict], component: str) -> list[dict]:
    return [r for r in rows if r.get("frame") is not None and r.get(component) is not None]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """One run written with the viewer's recording, one without (same run file)."""
    tmp = tmp_path_factory.mktemp("viewer")
    run, _ = make_run(steps=FRAMES)
    save_run(tmp / "r.npz", run)
    rrd = tmp / "live.rrd"
    assert main(["run", str(tmp / "r.npz"), *SETTINGS, "--viewer-save", str(rrd),
                 "--viewer-every", str(EVERY), "--out", str(tmp / "with")]) == 0
    assert main(["run", str(tmp / "r.npz"), *SETTINGS, "--out", str(tmp / "without")]) == 0
    return tmp, run, _entities(rrd)


def test_the_viewer_does_not_change_the_results(runs):
    tmp, _, _ = runs
    for name in ("trajectory_tum.txt", "vo_tum.txt"):
        assert (tmp / "with" / name).read_text() == (tmp / "without" / name).read_text()
    with np.load(tmp / "with" / "map.npz") as a, np.load(tmp / "without" / "map.npz") as b:
        assert np.array_equal(a["k"], b["k"]) and np.array_equal(a["S"], b["S"])


def test_live_recording_holds_every_frame(runs):
    tmp, run, ent = runs
    with np.load(tmp / "with" / "trace.npz") as trace:
        best, mean, ess = trace["best_pose"], trace["mean_pose"], trace["ess"]
    for entity, want in (("/world/pose/best", best), ("/world/pose/mean", mean)):
        rows = _temporal(ent[entity], "Points3D:positions")
        assert [r["frame"] for r in rows] == list(range(FRAMES))
        got = np.array([r["Points3D:positions"][0] for r in rows])
        np.testing.assert_allclose(got[:, :2], want[:, :2], atol=1e-5)
        assert np.all(got[:, 2] == 0)
    times = [r["time"].total_seconds() for r in _temporal(ent["/world/pose/best"],
                                                         "Points3D:positions")]
    np.testing.assert_allclose(times, run.timestamps, atol=1e-9)
    rows = _temporal(ent["/stats/ess"], "Scalars:scalars")
    np.testing.assert_allclose([r["Scalars:scalars"][0] for r in rows], ess, rtol=1e-6)
    clouds = _temporal(ent["/world/particles"], "Points3D:positions")
    assert [r["frame"] for r in clouds] == list(range(FRAMES))
    assert all(len(r["Points3D:positions"]) == PARTICLES for r in clouds)
    # the weighted mean lies inside its frame's cloud's bounding box
    for r, m in zip(clouds, mean):
        xy = np.array(r["Points3D:positions"])[:, :2]
        assert np.all(xy.min(0) - 1e-4 <= m[:2]) and np.all(m[:2] <= xy.max(0) + 1e-4)


def test_live_paths_grow_by_chunk_and_end_whole(runs):
    tmp, run, ent = runs
    chunk_ends = list(range(EVERY - 1, FRAMES - 1, EVERY)) + [FRAMES - 1]
    with np.load(tmp / "with" / "trace.npz") as trace:
        best = trace["best_pose"]
    vo = read_tum(tmp / "with" / "vo_tum.txt")[1]
    for entity, want in (("/world/path/best", best), ("/world/path/vo", vo),
                         ("/world/path/ground_truth", run.ground_truth)):
        rows = _temporal(ent[entity], "LineStrips3D:strips")
        assert [r["frame"] for r in rows] == chunk_ends
        assert [sum(map(len, r["LineStrips3D:strips"])) for r in rows] == \
            [e + 1 for e in chunk_ends]
        last = np.concatenate([np.array(s) for s in rows[-1]["LineStrips3D:strips"]])
        np.testing.assert_allclose(last[:, :2], want[:, :2], atol=1e-4)
    reported = _temporal(ent["/world/path/reported"], "LineStrips3D:strips")
    assert [r["frame"] for r in reported] == [FRAMES - 1]
    path = np.array(reported[0]["LineStrips3D:strips"][0])
    np.testing.assert_allclose(path[:, :2], read_tum(tmp / "with" / "trajectory_tum.txt")[1][:, :2],
                               atol=1e-4)


def test_live_map_is_placed_and_oriented_as_map_npz(runs):
    tmp, _, ent = runs
    maps = _temporal(ent["/world/map"], "GridMap:data")
    # one per chunk's end, then the results' map at the last frame
    assert [r["frame"] for r in maps] == list(range(EVERY - 1, FRAMES - 1, EVERY)) + \
        [FRAMES - 1, FRAMES - 1]
    with np.load(tmp / "with" / "map.npz") as m:
        k, origin, res = m["k"], m["origin"], float(m["resolution"])
    nx, ny = k.shape
    for row in maps[-2:]:  # the last chunk's map and the results' are the best particle's
        fmt = row["GridMap:format"][0]
        assert (fmt["width"], fmt["height"]) == (nx, ny)
        np.testing.assert_allclose(row["GridMap:translation"][0][:2], origin, atol=1e-5)
        assert row["GridMap:cell_size"][0] == pytest.approx(res, rel=1e-6)
        rgba = row["GridMap:data"].reshape(ny, nx, 4)
        # top row first: image row r is cell row j = ny - 1 - r; opaque exactly where k > 0
        opaque = rgba[::-1, :, 3].T > 0
        assert np.array_equal(opaque, k > 0) and opaque.any() and not opaque.all()


def test_gslam_view_shows_a_finished_run(runs, capsys):
    tmp, _, _ = runs
    rrd = tmp / "view.rrd"
    assert main(["view", str(tmp / "with"), "--save", str(rrd)]) == 0
    assert f"{FRAMES} frames" in capsys.readouterr().out
    ent = _entities(rrd)
    with np.load(tmp / "with" / "trace.npz") as trace:
        best, ess = trace["best_pose"], trace["ess"]
    rows = _temporal(ent["/world/pose/best"], "Points3D:positions")
    np.testing.assert_allclose([r["Points3D:positions"][0][:2] for r in rows], best[:, :2],
                               atol=1e-5)
    assert len(_temporal(ent["/stats/ess"], "Scalars:scalars")) == len(ess)
    for entity in ("/world/path/reported", "/world/path/vo", "/world/path/ground_truth"):
        static = [r for r in ent[entity] if r.get("frame") is None]
        assert len(static) == 1 and sum(map(len, static[0]["LineStrips3D:strips"])) == FRAMES
    assert [r.get("frame") for r in ent["/world/map"]] == [None]
    assert "/world/particles" not in ent or not _temporal(ent["/world/particles"],
                                                         "Points3D:positions")


def test_live_stream_logs_each_pushed_frame(tmp_path):
    from gslam_jax.app.viewer import open_viewer
    from gslam_jax.config import Config, FilterSection, LocalMapSection
    from gslam_jax.driver.online import Online

    run, _ = make_run(steps=12)
    config = Config(filter=FilterSection(particles=PARTICLES),
                    localmap=LocalMapSection(max_range=5.0, travel=1.0))
    live = Online(config, 30.0, local_size=run.local_maps.shape[1])
    viewer = open_viewer("live", save=tmp_path / "live.rrd")
    pushed = []
    for t in range(run.num_frames):
        m = run.obs_index[t]
        frame = live.push(run.controls[t], run.local_maps[m] if m >= 0 else None,
                          run.timestamps[t])
        viewer.online(live, frame, run.timestamps[t], map_every=5)
        pushed.append(frame.pose)
    viewer.close()
    ent = _entities(tmp_path / "live.rrd")
    rows = _temporal(ent["/world/pose/best"], "Points3D:positions")
    np.testing.assert_allclose([r["Points3D:positions"][0][:2] for r in rows],
                               np.array(pushed)[:, :2], atol=1e-6)
    clouds = _temporal(ent["/world/particles"], "Points3D:positions")
    assert len(clouds) == run.num_frames
    assert all(len(r["Points3D:positions"]) == PARTICLES for r in clouds)
    last = live.particles().pose  # the last frame's cloud is the particles Online holds
    np.testing.assert_allclose(np.array(clouds[-1]["Points3D:positions"])[:, :2], last[:, :2],
                               atol=1e-6)
    assert [r["frame"] for r in _temporal(ent["/world/map"], "GridMap:data")] == [0, 5, 10]


def test_unknown_frames_split_a_path_and_large_clouds_are_thinned():
    from gslam_jax.app.viewer import RunViewer, finite_strips

    xy = np.arange(20.0).reshape(10, 2)
    xy[[0, 4, 5, 9]] = np.nan
    strips = finite_strips(xy)
    assert [len(s) for s in strips] == [3, 3]  # frames 1-3 and 6-8
    np.testing.assert_array_equal(strips[1][:, :2], xy[6:9])
    assert finite_strips(np.full((3, 3), np.nan)) == []
    viewer = RunViewer(rr.RecordingStream("thin"), max_particles=4)
    poses = np.random.default_rng(0).normal(size=(2, 10, 3))
    thin = viewer._particles(poses)
    assert thin.shape == (2, 4, 3)
    np.testing.assert_array_equal(thin, poses[:, [0, 3, 6, 9]])  # evenly strided, both ends


def test_view_names_a_folder_that_is_not_a_run(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert main(["view", str(tmp_path / "empty"), "--save", str(tmp_path / "x.rrd")]) == 2
    assert "has no map.npz" in capsys.readouterr().err


@pytest.fixture
def no_work(monkeypatch):
    def boom(*args, **kwargs):
        raise AssertionError("work started before the viewer options were checked")
    monkeypatch.setattr("gslam_jax.driver.slam.run_slam", boom)
    monkeypatch.setattr("gslam_jax.app.pipeline.prepare_source", boom)


def test_missing_extra_is_named_before_any_work(tmp_path, capsys, monkeypatch, no_work):
    monkeypatch.setitem(sys.modules, "rerun", None)  # import rerun -> ImportError
    assert main(["run", "--viewer-save", str(tmp_path / "x.rrd"),
                 "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "--viewer-save needs the optional extra 'viewer'" in err and "gslam-jax[viewer]" in err
    assert main(["view", str(tmp_path), "--save", str(tmp_path / "x.rrd")]) == 2
    assert "gslam-jax[viewer]" in capsys.readouterr().err


def test_viewer_without_a_display_points_to_the_file(tmp_path, capsys, monkeypatch, no_work):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(sys, "platform", "linux")
    assert main(["run", "--viewer", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "--viewer: no display" in err and "--viewer-save FILE.rrd" in err


def test_viewer_every_alone_is_refused(tmp_path, capsys, no_work):
    assert main(["run", "--viewer-every", "5", "--out", str(tmp_path / "o")]) == 2
    assert "--viewer-every" in capsys.readouterr().err


def test_a_map_on_the_start_axes_is_shown_turned_and_the_poses_in_the_runs_frame(tmp_path):
    """[map] axes = "start" on a run that starts turned: the filter runs on the robot's start
    axes, the recording shows the poses in the run's frame (as trace.npz) and the map turned by
    map.npz's heading about its frame's origin."""
    import math

    run, _ = make_run(steps=FRAMES)
    run = run._replace(initial_pose=np.array([0.3, -0.2, 0.7]))
    save_run(tmp_path / "r.npz", run)
    rrd = tmp_path / "live.rrd"
    assert main(["run", str(tmp_path / "r.npz"), *SETTINGS, "--set", "map.axes=start",
                 "--viewer-save", str(rrd), "--viewer-every", str(EVERY),
                 "--out", str(tmp_path / "out")]) == 0
    ent = _entities(rrd)
    with np.load(tmp_path / "out" / "trace.npz") as trace:
        best = trace["best_pose"]
    rows = _temporal(ent["/world/pose/best"], "Points3D:positions")
    np.testing.assert_allclose([r["Points3D:positions"][0][:2] for r in rows], best[:, :2],
                               atol=1e-4)
    with np.load(tmp_path / "out" / "map.npz") as m:
        origin, heading = m["origin"], float(m["heading"])
    assert heading == pytest.approx(0.7)
    c, s = math.cos(heading), math.sin(heading)
    corner = [c * origin[0] - s * origin[1], s * origin[0] + c * origin[1]]
    for row in _temporal(ent["/world/map"], "GridMap:data")[-2:]:  # last chunk's, results'
        np.testing.assert_allclose(row["GridMap:translation"][0][:2], corner, atol=1e-4)
        turn = row["GridMap:rotation_axis_angle"][0]
        assert turn["axis"] == pytest.approx([0.0, 0.0, 1.0])
        assert turn["angle"] == pytest.approx(heading, abs=1e-6)


def test_gslam_view_opens_a_merge_folder(runs, tmp_path, capsys):
    """Before: "has no trajectory_tum.txt: give a gslam run results folder". A merge folder
    (as ``gslam merge`` writes it) shows the merged map and each run's path in its frame."""
    from gslam_jax.app.merge import write_merge
    from gslam_jax.gridmap import load_map
    from gslam_jax.gridmap.merge import MapRun, Merged

    tmp, _, _ = runs
    grid = load_map(tmp / "with")
    times, path = read_tum(tmp / "with" / "trajectory_tum.txt")
    pose_b = np.array([1.0, -0.5, 0.3])
    runs_ = [MapRun("a", grid, times, path), MapRun("b", grid, times, path)]
    write_merge(tmp_path, runs_, Merged(grid, [np.zeros(3), pose_b], [None, None]))
    rrd = tmp_path.parent / f"{tmp_path.name}-merge.rrd"
    assert main(["view", str(tmp_path), "--save", str(rrd)]) == 0
    assert "2 runs merged" in capsys.readouterr().out
    ent = _entities(rrd)
    for entity, file in (("/world/path/run0_a", "trajectory_0_a_tum.txt"),
                         ("/world/path/run1_b", "trajectory_1_b_tum.txt")):
        strips = ent[entity][0]["LineStrips3D:strips"]
        np.testing.assert_allclose(np.array(strips[0])[:, :2],
                                   read_tum(tmp_path / file)[1][:, :2], atol=1e-5)
    # run b placed by its pose (x, y, heading): its path is a rigid motion of a's
    c, s = np.cos(pose_b[2]), np.sin(pose_b[2])
    want = path[:, :2] @ np.array([[c, s], [-s, c]]) + pose_b[:2]
    got = np.array(ent["/world/path/run1_b"][0]["LineStrips3D:strips"][0])[:, :2]
    np.testing.assert_allclose(got, want, atol=1e-4)
    assert [r.get("frame") for r in ent["/world/map"]] == [None]


def test_view_save_refuses_an_existing_file_unless_overwrite(runs, tmp_path, capsys):
    """Before: ``gslam view A --save FILE`` replaced FILE without asking."""
    tmp, _, _ = runs
    rrd = tmp_path / "old.rrd"
    rrd.write_bytes(b"the user's recording")
    assert main(["view", str(tmp / "with"), "--save", str(rrd)]) == 2
    assert f"--save {rrd}: exists (--overwrite replaces it)" in capsys.readouterr().err
    assert rrd.read_bytes() == b"the user's recording"
    assert main(["view", str(tmp / "with"), "--save", str(rrd), "--overwrite"]) == 0
    assert "/world/path/reported" in _entities(rrd)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.rrd"]  # no temporary left


@pytest.mark.parametrize("failure", ["bad-path", "refused-out", "exists"])
def test_viewer_save_keeps_an_existing_file_when_the_run_fails_at_once(
        runs, tmp_path, capsys, failure):
    """Before: --viewer-save FILE was opened (emptied) before the run's other checks, so a bad
    --path or a refused --out replaced the user's file by an empty recording."""
    tmp, _, _ = runs
    rrd = tmp_path / "old.rrd"
    rrd.write_bytes(b"the user's recording")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("x")
    argv = {"bad-path": ["--source", "kitti", "--path", str(tmp_path / "nothing"),
                         "--overwrite", "--out", str(tmp_path / "o")],
            "refused-out": [str(tmp / "r.npz"), "--out", str(tmp_path / "full"), "--overwrite"],
            "exists": [str(tmp / "r.npz"), "--out", str(tmp_path / "o")]}[failure]
    assert main(["run", *argv, "--viewer-save", str(rrd)]) == 2
    assert capsys.readouterr().err.startswith("gslam: error:")
    assert rrd.read_bytes() == b"the user's recording"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["full", "old.rrd"]
