"""Loop closure: the revisit, the revisit error, the map offset and the verdict
(gslam_jax.evaluation.loops), and a CI-sized run of experiments/loop_closure.py."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from gslam_jax.config import Config, apply_overrides
from gslam_jax.datasets.sim_path import simulate_path
from gslam_jax.evaluation import loops
from gslam_jax.gridmap.grid import GridMap, arc_length
from gslam_jax.sim.vonoise import VO_PROFILES
from gslam_jax.vo.localmap import localmap_params

SMALL = apply_overrides(Config(), ["localmap.max_range=5"])  # 64-cell local maps: CI-sized


def _circle(length: float, extra: float, step: float = 0.25) -> np.ndarray:
    """Poses (x, y, yaw) around a circle of perimeter ``length``, then ``extra`` metres on."""
    r = length / (2 * np.pi)
    phi = np.arange(0.0, (length + extra) / r, step / r)
    return np.stack([r * np.sin(phi), r * (1 - np.cos(phi)), phi], axis=1)


def _rel(poses: np.ndarray, i: int, j: int) -> complex:
    """Independently: position of j in the frame of i, as a complex number."""
    z = poses[:, 0] + 1j * poses[:, 1]
    return (z[j] - z[i]) * np.exp(-1j * poses[i, 2])


def _dead_reckon(true: np.ndarray, heading_drift: float) -> np.ndarray:
    """The true steps integrated with a heading error growing by ``heading_drift`` rad per
    metre: an open, drifted estimate (no map correction)."""
    z = true[:, 0] + 1j * true[:, 1]
    steps = np.diff(z)
    arc = np.concatenate([[0.0], np.cumsum(np.abs(steps))])
    turned = steps * np.exp(1j * heading_drift * arc[1:])
    est_z = np.concatenate([[z[0]], z[0] + np.cumsum(turned)])
    return np.stack([est_z.real, est_z.imag, true[:, 2] + heading_drift * arc], axis=1)


def test_revisit_is_the_nearest_return_after_the_loop() -> None:
    true = _circle(60.0, 20.0)
    rv = loops.find_revisit(true, start_m=10.0, min_loop_m=30.0)
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(true[:, :2], axis=0).T))])
    i = int(np.argmax(arc >= 10.0))
    dist = [math.hypot(*(true[k, :2] - true[i, :2])) if arc[k] >= arc[i] + 30 else np.inf
            for k in range(len(true))]
    assert (rv.i, rv.j) == (i, int(np.argmin(dist)))
    assert rv.gap_m < 0.2 and abs(rv.loop_m - 60.0) < 0.3
    # a path that never comes back has no revisit
    straight = np.stack([np.arange(200) * 0.5, np.zeros(200), np.zeros(200)], axis=1)
    assert loops.find_revisit(straight, 10.0, 30.0) is None


def test_revisit_error_closed_and_open_paths() -> None:
    true = _circle(100.0, 20.0)
    rv = loops.find_revisit(true, 10.0, 50.0)
    rng = np.random.default_rng(0)
    # closed: the truth moved rigidly (any frame) with 5 cm jitter
    a, t = 0.7, np.array([3.0, -8.0])
    c, s = math.cos(a), math.sin(a)
    closed = true.copy()
    closed[:, :2] = true[:, :2] @ np.array([[c, -s], [s, c]]).T + t
    closed[:, 2] += a
    closed[:, :2] += rng.normal(0.0, 0.05, closed[:, :2].shape)
    want = abs(_rel(closed, rv.i, rv.j) - _rel(true, rv.i, rv.j))
    got = loops.revisit_error(true, closed, rv.i, rv.j)
    assert got == pytest.approx(want, abs=1e-9) and got < 0.2
    # open: dead reckoning with a heading drift of 1 mrad per metre
    drifted = _dead_reckon(true, 0.001)
    want = abs(_rel(drifted, rv.i, rv.j) - _rel(true, rv.i, rv.j))
    got = loops.revisit_error(true, drifted, rv.i, rv.j)
    assert got == pytest.approx(want, abs=1e-9) and got > loops.TOLERANCE
    # and the estimate's own rigid motion does not change it
    moved = drifted.copy()
    moved[:, :2] = drifted[:, :2] @ np.array([[c, -s], [s, c]]).T + t
    moved[:, 2] += a
    assert loops.revisit_error(true, moved, rv.i, rv.j) == pytest.approx(got, abs=1e-9)


def _offset_brute_force(first: GridMap, second: GridMap, max_shift: float,
                        min_cells: int = 200) -> tuple[float, float]:
    """map_offset by a loop over the shifts, np.corrcoef at each."""
    a, b = first.expected_std(), second.expected_std()
    ka, kb = first.k > 0, second.k > 0
    s = round(max_shift / first.resolution)
    H, W = a.shape
    best = (-np.inf, np.nan)
    for di in range(-s, s + 1):
        for dj in range(-s, s + 1):
            both = np.zeros_like(ka)
            i0, i1, j0, j1 = max(0, -di), min(H, H - di), max(0, -dj), min(W, W - dj)
            both[i0:i1, j0:j1] = ka[i0:i1, j0:j1] & kb[i0 + di:i1 + di, j0 + dj:j1 + dj]
            if both.sum() < min_cells:
                continue
            x = a[both]
            y = np.roll(b, (-di, -dj), (0, 1))[both]
            corr = np.corrcoef(x, y)[0, 1]
            if corr > best[0]:
                best = (corr, math.hypot(di, dj) * first.resolution)
    return best[1], best[0]


def test_map_offset_finds_a_shifted_copy() -> None:
    """Random texture in a known patch; the second map is the first shifted by whole cells,
    or another texture partly overlapping (against a loop over the shifts)."""
    rng = np.random.default_rng(3)
    res = 0.2
    k = np.zeros((80, 90))
    k[20:60, 25:70] = 5.0
    S = k * rng.gamma(2.0, 1.0, k.shape)
    first = GridMap(k, S, (0.0, 0.0), res)
    for di, dj in [(0, 0), (3, 0), (-4, 6), (10, 0)]:
        second = GridMap(np.roll(k, (di, dj), (0, 1)), np.roll(S, (di, dj), (0, 1)),
                         (0.0, 0.0), res)
        offset, corr = loops.map_offset(first, second, max_shift=3.0)
        assert offset == pytest.approx(math.hypot(di, dj) * res) and corr == pytest.approx(1.0)
    k2 = np.zeros_like(k)
    k2[30:75, 10:60] = rng.integers(1, 4, (45, 50))
    other = GridMap(k2, k2 * rng.gamma(2.0, 1.0, k.shape) + 0.5 * S * (k2 > 0), (0.0, 0.0), res)
    got = loops.map_offset(first, other, max_shift=1.6)
    want = _offset_brute_force(first, other, max_shift=1.6)
    assert got[0] == pytest.approx(want[0]) and got[1] == pytest.approx(want[1], abs=1e-5)
    assert 0.0 < got[1] < 0.9
    # the NumPy expected std is that of the filter's cells (JAX)
    from gslam_jax.rbpf import cells
    k3 = np.array([0.0, 0.5, 1.0, 2.0, 3.0, 40.0])
    S3 = np.array([0.0, 0.2, 0.3, 0.4, 0.5, 6.0])
    np.testing.assert_allclose(loops.expected_std(k3, S3), np.asarray(cells.expected_std(k3, S3)),
                               rtol=1e-5, equal_nan=True)
    with pytest.raises(ValueError, match="one grid"):
        loops.map_offset(first, GridMap(k, S, (0.2, 0.0), res))


@pytest.fixture(scope="module")
def noisy_loop(tmp_path_factory):
    """A 30 m circle driven with 4x the Mars Yard VO noise: VO misses the start by > 1 m."""
    from experiments.loop_paths import circle_file

    file = circle_file(tmp_path_factory.mktemp("loop"), 30.0, 15.0)
    vo = VO_PROFILES["mars-yard-a"].scaled(4.0)
    run, _ = simulate_path(file, seed=1, course="mars-yard-a", vo_noise=vo,
                           params=localmap_params(SMALL))
    return file, vo, run


def test_closure_verdict_on_a_simulated_loop(noisy_loop) -> None:
    _, _, run = noisy_loop
    gt = run.ground_truth
    rv = loops.find_revisit(gt, 10.0, 15.0)
    assert rv is not None and abs(rv.loop_m - 30.0) < 1.0
    truth = loops.closure(run, gt, rv)
    # at the true poses the copies coincide to within a cell (the local cells' rounding)
    assert truth.closed and truth.error_m == 0.0
    assert truth.map_offset_m <= math.sqrt(2) * run.resolution + 1e-9
    # the second visit laid 2 m off: both figures see it
    arc = arc_length(gt)
    off = gt.copy()
    off[np.abs(arc - arc[rv.j]) <= 5.0, 1] += 2.0
    doubled = loops.closure(run, off, rv)
    assert not doubled.closed and abs(doubled.map_offset_m - 2.0) < 0.4
    # VO only: no map correction, so its revisit error is the VO's drift (> 1 m): open
    vo = run.vo_poses()
    vo_err = abs(_rel(vo, rv.i, rv.j) - _rel(gt, rv.i, rv.j))
    assert vo_err > loops.TOLERANCE  # the premise, computed independently
    verdict = loops.closure(run, vo, rv)
    assert verdict.error_m == pytest.approx(vo_err) and not verdict.closed


def test_experiment_pipeline_gives_a_verdict(noisy_loop) -> None:
    """experiments/loop_closure.py end to end at CI size: one seed, J = 8, the motion proposal."""
    from experiments.loop_closure import Loop, run_loop
    from experiments.loop_summary import summary

    file, vo, run = noisy_loop
    rows = run_loop(Loop("circle-30", "circle", 30.0, file), 1, SMALL, [8], ["motion"],
                    math.inf, course="mars-yard-a", vo_noise=vo)
    (row,) = rows
    assert isinstance(row["closed"], bool) and math.isfinite(row["error_m"])
    assert row["closed"] == (row["error_m"] <= 1.0 and row["map_offset_m"] <= 1.0)
    rv = loops.Revisit(*row["revisit"])
    vo_err = abs(_rel(run.vo_poses(), rv.i, rv.j) - _rel(run.ground_truth, rv.i, rv.j))
    assert row["vo_error_m"] == pytest.approx(vo_err) and row["vo_closed"] is False
    arc = arc_length(run.ground_truth)  # the cloud is read before the start is in view
    before = arc[rv.j] - arc[row["approach_frame"]]
    reach = SMALL.localmap.max_range + 2.0 + 10.0  # sensor range, APPROACH_M, START_M
    assert reach <= before < reach + 0.5
    counts = [row[f"approach_within_{r}m"] for r in (1, 2, 3, 5)]
    assert 0 <= counts[0] and counts == sorted(counts) and counts[-1] <= 8
    assert (row["approach_within_1m"] > 0) == (row["approach_nearest_m"] <= 1.0)
    assert -180.0 <= row["approach_nearest_heading_deg"] <= 180.0
    s = summary(rows)["motion J=8"]
    assert s["rates"][30.0] == (float(row["closed"]), 1)
    assert s["longest"] == (30.0 if row["closed"] else None)
    # the densest particle's path, judged the same way
    assert math.isfinite(row["mode_error_m"])
    assert row["mode_closed"] == (row["mode_error_m"] <= 1.0 and row["mode_map_offset_m"] <= 1.0)
    s = summary(rows, verdict="mode")["motion J=8"]
    assert s["rates"][30.0] == (float(row["mode_closed"]), 1)
    # and the mean over its 1 m neighbourhood
    assert math.isfinite(row["mode_mean_error_m"])
    assert row["mode_mean_closed"] == (row["mode_mean_error_m"] <= 1.0
                                       and row["mode_mean_map_offset_m"] <= 1.0)
    s = summary(rows, verdict="mode_mean")["motion J=8"]
    assert s["rates"][30.0] == (float(row["mode_mean_closed"]), 1)


def _rows_file(folder, name: str, rows: list[dict]):
    path = folder / name
    path.write_text(json.dumps({"settings": {}, "environment": {}, "rows": rows}))
    return path


def _row(seed: int, J: int, length: float, closed: bool) -> dict:
    return {"loop": f"circle-{length:g}", "kind": "circle", "length_m": length, "seed": seed,
            "proposal": "motion", "particles": J, "closed": closed, "vo_closed": False}


def test_runs_made_apart_are_summarised_together(tmp_path, capsys) -> None:
    """--from-json pools the rows of several --json files (a seed per process) into one
    summary, and refuses a run found twice, naming the file."""
    from experiments.loop_closure import main

    a = _rows_file(tmp_path, "a.json", [_row(s, 200, 400.0, s != 1) for s in range(5)])
    b = _rows_file(tmp_path, "b.json", [_row(0, 2000, 800.0, True), _row(1, 2000, 800.0, False)])
    c = _rows_file(tmp_path, "c.json", [_row(s, 2000, 800.0, True) for s in (2, 3, 4)])
    assert main(["--from-json", str(a), str(b), str(c)]) == 0
    out = capsys.readouterr().out
    assert "motion J=200: 400 m 80% (5); longest closed in >= 80 %: 400 m" in out
    assert "motion J=2000: 800 m 80% (5); longest closed in >= 80 %: 800 m" in out
    with pytest.raises(SystemExit, match=r"c\.json: run \('circle-800', 2, 'motion', 2000\) "
                                         r"is also in .*c2\.json"):
        c2 = _rows_file(tmp_path, "c2.json", [_row(2, 2000, 800.0, True)])
        main(["--from-json", str(c2), str(c)])
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(SystemExit, match=r"bad\.json: not a loop_closure --json file"):
        main(["--from-json", str(tmp_path / "bad.json")])
    # the densest particle's verdict where the rows have it, a named error where they do not
    # (and split by the cloud before the revisit: seeds 1 and 3 had a particle within 1 m of
    # the truth, 0 and 2 none; seed 4 did not record its cloud and is left out of the split)
    m = _rows_file(tmp_path, "m.json", [
        dict(_row(s, 200, 400.0, False), mode_closed=s > 0,
             **({"approach_within_1m": s % 2} if s < 4 else {})) for s in range(5)])
    assert main(["--from-json", str(m), "--verdict", "mode"]) == 0
    out = capsys.readouterr().out
    assert "motion J=200: 400 m 80% (5)" in out
    assert "closed with a particle within 1 m before the revisit: 2/2; with none: 1/2" in out
    with pytest.raises(SystemExit, match=r"circle-400 seed 0 motion J=200: no mode verdict"):
        main(["--from-json", str(a), "--verdict", "mode"])


def test_the_plot_draws_circles_and_real_paths_apart(tmp_path) -> None:
    """--plot: one curve per (proposal, J) and family, so a real path's cut of 478 m closed
    less often than one of 559 m is not joined to the circles' curve."""
    import matplotlib.image as mpimg

    from experiments.loop_closure import main
    from experiments.loop_summary import curves, family, read_rows

    cut = dict(_row(0, 200, 478.4, False), loop="kitti08-795-1417", kind="kitti")
    assert (family(_row(0, 200, 400.0, True)), family(cut)) == ("circles", "real paths")
    a = _rows_file(tmp_path, "a.json", [_row(s, 200, 400.0, s != 1) for s in range(5)]
                   + [dict(cut, seed=s, closed=s == 0) for s in range(5)])
    png = tmp_path / "loops.png"
    assert main(["--from-json", str(a), "--plot", str(png)]) == 0
    assert mpimg.imread(png).shape[:2] == (378, 630)  # figsize 7 x 4.2 at 90 dpi
    assert curves(read_rows([a])) == {("motion J=200", "circles"): ([400.0], [0.8]),
                                      ("VO only", "circles"): ([400.0], [0.0]),
                                      ("motion J=200", "real paths"): ([478.4], [0.2]),
                                      ("VO only", "real paths"): ([478.4], [0.0])}


def test_resume_runs_only_the_runs_missing_from_the_file(tmp_path, monkeypatch, capsys) -> None:
    """--resume keeps the runs already in --json, simulates only the missing ones, and refuses
    a file made with other run settings, naming the setting."""
    import experiments.loop_closure as lc

    settings = {"config": None, "set": [], "store": "auto", "course": "mars-yard-a",
                "overlap": 20.0, "margin_per_m": 0.1, "radius": 2.0}
    file = tmp_path / "runs.json"
    file.write_text(json.dumps({"settings": settings, "environment": {},
                                "rows": [_row(1, 8, 30.0, True)]}))

    class Simulated(Exception):
        pass

    def simulate(file_, length, seed, *a, **k):
        raise Simulated(seed)

    monkeypatch.setattr(lc, "simulate_loop", simulate)
    args = ["--circles", "30", "--particles", "8", "--proposals", "motion", "--json", str(file),
            "--resume"]
    assert lc.main(args + ["--seeds", "1"]) == 0  # nothing left to run: nothing simulated
    assert "motion J=8: 30 m 100% (1)" in capsys.readouterr().out
    assert json.loads(file.read_text())["rows"] == [_row(1, 8, 30.0, True)]
    with pytest.raises(Simulated, match="2"):
        lc.main(args + ["--seeds", "1", "2"])
    with pytest.raises(SystemExit, match=r"runs\.json: --resume with --course 'arroyo-a'"):
        lc.main(args + ["--seeds", "1", "--course", "arroyo-a"])
    # a file written before --vo-scale existed was made with the VO's own noise
    with pytest.raises(SystemExit, match=r"--resume with --vo-scale 0\.3, but its runs were "
                                         r"made with 1\.0"):
        lc.main(args + ["--seeds", "1", "--vo-scale", "0.3"])


def test_the_vo_and_noise_scales_reach_the_simulation_and_the_filter(monkeypatch) -> None:
    """--vo-scale multiplies every std of the course's VO profile the loop is driven with,
    --vo-failures its rate of failures, --noise-scale the alphas of the filter's motion
    model."""
    import experiments.loop_closure as lc
    from gslam_jax.config import layered_config
    from gslam_jax.sim.vonoise import VO_PROFILES

    seen = {}

    class Simulated(Exception):
        pass

    def simulate(file_, length, seed, config, course, max_frames, margin, vo_noise):
        seen.update(motion=config.motion, vo=vo_noise)
        raise Simulated

    monkeypatch.setattr(lc, "simulate_loop", simulate)
    with pytest.raises(Simulated):
        lc.main(["--circles", "30", "--particles", "8", "--proposals", "motion", "--seeds", "1",
                 "--course", "arroyo-a", "--vo-scale", "0.3", "--noise-scale", "2",
                 "--vo-failures", "0.5"])
    given, profile = layered_config(None, "arroyo-a", []).motion, VO_PROFILES["arroyo-a"]
    assert seen["vo"].heading_bias_std == pytest.approx(0.3 * profile.heading_bias_std)
    assert seen["vo"].alpha_theta_d == pytest.approx(0.3 * profile.alpha_theta_d)
    assert seen["vo"].failure_rate == pytest.approx(0.5 * profile.failure_rate)
    assert seen["vo"].wheel_alpha_theta_d == profile.wheel_alpha_theta_d
    for name in ("alpha_d", "alpha_theta_d", "alpha_theta"):
        assert getattr(seen["motion"], name) == pytest.approx(2 * getattr(given, name))


def test_approach_cloud_reads_its_frame_of_a_hand_made_cloud() -> None:
    """ApproachCloud on two chunks of a hand-made cloud: it reads only its own frame; the
    distances, counts and the nearest particle's heading error (wrapped across +-pi) are the
    ones worked out by hand."""
    from types import SimpleNamespace

    from experiments.loop_closure import ApproachCloud

    truth = np.zeros((6, 3))
    truth[:, 0] = np.arange(6.0)
    truth[:, 2] = math.pi - 0.01  # the truth heads just short of +pi
    pose = np.zeros((6, 4, 3))
    pose[:, :, :2] = truth[:, None, :2] + np.array([[0.0, 0.6], [3.0, 0.0], [0.0, -1.5],
                                                    [40.0, 0.0]])
    pose[:, :, 2] = -math.pi + 0.02  # 0.03 rad to the left of the truth, across the wrap
    pose[4, 2, 2] = 0.0
    run = SimpleNamespace(ground_truth=truth)
    cloud = ApproachCloud(4)
    for start in (0, 3):
        n = 3
        cloud(SimpleNamespace(start=start, best_pose=truth[start:start + n], run=run,
                              info=SimpleNamespace(pose=pose[start:start + n])))
    assert cloud.nearest_m == pytest.approx(0.6)
    assert cloud.within == {"approach_within_1m": 1, "approach_within_2m": 2,
                            "approach_within_3m": 3, "approach_within_5m": 3}
    assert cloud.nearest_heading_deg == pytest.approx(math.degrees(0.03))


def test_kitti_cuts_skip_a_loop_that_holds_a_shorter_one(tmp_path) -> None:
    """A path 60 m east, round a 200 m circle back to its start, then 65 m west over the spur
    again (a KITTI pose file): pose 0's first return closes a 320 m loop, but the filter meets
    the spur again at the circle's end and closes the 200 m loop first. The cut asked for at
    320 m is the circle; without the check (a lead of any length) it is the outer loop."""
    from experiments.loop_paths import kitti_cuts

    step, r = 0.5, 200.0 / (2 * np.pi)
    phi = np.arange(0.0, 2 * np.pi, step / r)
    x = np.concatenate([np.arange(0.0, 60.0, step), 60 + r * np.sin(phi),
                        np.arange(60.0, -5.0, -step)])
    y = np.concatenate([np.zeros(120), r * (1 - np.cos(phi)), np.zeros(130)])
    rows = np.zeros((len(x), 12))
    rows[:, [0, 5, 10]] = 1.0
    rows[:, 3], rows[:, 11] = x, y  # KITTI camera frame: the ground plane is (x, z)
    file = tmp_path / "loop.txt"
    np.savetxt(file, rows)
    (a, b, length), = kitti_cuts(file, [320.0], radius=2.0, every=1)
    assert 195.0 <= length <= 205.0  # the circle, from where its end meets the spur
    (a, b, length), = kitti_cuts(file, [320.0], radius=2.0, every=1, lead_m=1e9)
    assert a == 0 and 316.0 <= length <= 320.0  # back within 2 m of x = 0 at x = 2
    # two lengths nearest the same cut give it once, so it is not driven twice
    assert kitti_cuts(file, [250.0, 320.0], radius=2.0, every=1) == \
        kitti_cuts(file, [320.0], radius=2.0, every=1)
    # nor a near copy: 198 m from pose 101 (x = 50.5) back to pose 499 is the circle from pose
    # 122 (x = 61) again, entered and left within 20 m of travel of it
    cuts = kitti_cuts(file, [196.0, 199.0], radius=2.0, every=1)
    assert len(cuts) == 1 and 195.0 <= cuts[0][2] <= 205.0
