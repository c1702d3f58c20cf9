"""experiments.error_timeline: errors with no fit, the first distance past a limit, and the
rows and summaries of hand-made paths (no filter run); one short run end to end."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np

from experiments import error_timeline
from experiments.error_timeline import first_exceeding, pose_errors, timeline


def _straight(T: int = 101, step: float = 0.5) -> np.ndarray:
    return np.stack([np.arange(T) * step, np.zeros(T), np.zeros(T)], axis=1)


def test_pose_errors_have_no_fit_and_wrap_the_heading():
    truth = np.array([[0.0, 0.0, math.pi - 0.1], [1.0, 0.0, 0.0]])
    path = np.array([[3.0, 4.0, -math.pi + 0.1], [1.0, 0.0, 0.0]])
    position, heading = pose_errors(path, truth)
    np.testing.assert_allclose(position, [5.0, 0.0])
    np.testing.assert_allclose(heading, [math.degrees(0.2), 0.0], atol=1e-9)


def test_first_exceeding():
    dist = np.array([0.0, 1.0, 2.0, 3.0])
    assert first_exceeding(np.array([0.0, 0.5, 2.0, 0.0]), 1.0, dist) == 2.0
    assert first_exceeding(np.array([0.0, 0.5, 1.0, 0.0]), 1.0, dist) is None  # not beyond


def test_timeline_places_an_error_where_it_was_made():
    truth = _straight()  # 50 m at 0.5 m a frame
    vo = truth.copy()
    vo[:, 1] += 0.1  # the VO 0.1 m off throughout
    turned = truth.copy()
    turned[60:, 1] += 2.0  # 2 m to the side from frame 60 (30 m), and turned 5 deg there
    turned[60:, 2] += math.radians(5.0)
    run = SimpleNamespace(ground_truth=truth)
    res = {"kept": SimpleNamespace(path=truth.copy(), vo_path=vo, seconds=1.0,
                                   compile_seconds=0.5),
           "lost": SimpleNamespace(path=turned, vo_path=vo, seconds=2.0, compile_seconds=0.0)}
    table = timeline(run, res, every=10.0, heading_limit=3.0, margin=0.5)
    assert [r["distance_m"] for r in table["rows"]] == [0.0, 10.0, 20.0, 30.0, 40.0, 50.0]
    for r in table["rows"]:
        np.testing.assert_allclose(r["vo"], [0.1, 0.0], atol=1e-12)
        np.testing.assert_allclose(r["kept"], [0.0, 0.0], atol=1e-12)
        expect = [2.0, 5.0] if r["distance_m"] >= 30.0 else [0.0, 0.0]
        np.testing.assert_allclose(r["lost"], expect, atol=1e-9)
    lost, kept = table["summary"]["lost"], table["summary"]["kept"]
    assert lost["heading_beyond_limit_at_m"] == 30.0
    assert lost["position_beyond_vo_at_m"] == 30.0
    assert lost["final_position_error_m"] == 2.0 and lost["seconds"] == 2.0
    assert kept["heading_beyond_limit_at_m"] is None
    assert kept["position_beyond_vo_at_m"] is None and kept["seconds"] == 1.5
    assert kept["rms_after_fit_m"] < 1e-9 < lost["rms_after_fit_m"]


def test_the_path_option_picks_the_filters_own_estimate():
    truth = _straight(21)
    off = truth.copy()
    off[:, 1] += 1.0  # the per-frame estimate 1 m to the side; the reported path on the truth
    res = {"a": SimpleNamespace(path=truth, mean_pose=off, best_pose=truth, vo_path=truth,
                                seconds=0.0, compile_seconds=0.0)}
    run = SimpleNamespace(ground_truth=truth)
    reported = timeline(run, res, every=5.0, heading_limit=3.0, margin=0.5)
    mean = timeline(run, res, every=5.0, heading_limit=3.0, margin=0.5, path="mean")
    assert all(r["a"][0] == 0.0 for r in reported["rows"])
    assert all(abs(r["a"][0] - 1.0) < 1e-12 for r in mean["rows"])
    assert mean["summary"]["a"]["position_beyond_vo_at_m"] == 0.0


def test_main_runs_each_variant_on_the_same_run(tmp_path, capsys):
    out = tmp_path / "t.json"
    assert error_timeline.main([
        "--courses", "mars-yard-a", "--max-frames", "60", "--every", "2",
        "--set", "filter.particles=4", "--path", "best",
        "--variant", "one", "--variant", "motion-noise-x2", "motion.alpha_d=0.1",
        "--out", str(out)]) == 0
    figures = json.loads(out.read_text())["mars-yard-a/sim0"]
    assert set(figures["summary"]) == {"one", "motion-noise-x2", "vo"}
    rows = figures["rows"]
    assert rows[0]["distance_m"] == 0.0 and rows[0]["one"] == [0.0, 0.0]
    # the VO column is the same run's VO whichever variant ran first
    assert all(len(r["vo"]) == 2 for r in rows)
    assert "heading beyond the limit" in capsys.readouterr().out
