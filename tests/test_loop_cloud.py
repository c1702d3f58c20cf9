"""experiments.loop_cloud: the per-stretch figures of a particle cloud, on a hand-made cloud
(no filter run), and its loop settings against ``loop_closure``'s."""

from __future__ import annotations

import argparse
import math

import numpy as np
import pytest

import experiments.loop_closure as lc
from experiments import loop_cloud
from experiments.loop_cloud import cloud_rows


T = 21  # frames of the hand-made cloud


def _square_cloud() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """21 frames 1 m apart along x (truth heading 0); four particles at the corners of a square
    of side 2 a around a point 1 m to the left of the truth, a = t / 10; headings +-0.1 rad
    around pi (wrapping across +-pi); resampled at frames 3, 12 and 13."""
    truth = np.stack([np.arange(T, dtype=float), np.zeros(T), np.zeros(T)], axis=1)
    a = np.arange(T) / 10.0
    corners = np.array([[1, 1], [1, -1], [-1, 1], [-1, -1]], float)
    poses = np.zeros((T, 4, 3))
    poses[:, :, :2] = truth[:, None, :2] + np.array([0.0, 1.0]) + a[:, None, None] * corners
    poses[:, :, 2] = math.pi + np.array([0.1, -0.1, 0.1, -0.1])
    resampled = np.zeros(T, bool)
    resampled[[3, 12, 13]] = True
    return truth, poses, resampled


def test_cloud_rows_on_a_hand_made_cloud():
    truth, poses, resampled = _square_cloud()
    vo = truth + np.array([0.0, 0.5, 0.0])
    best = poses[:, 0]
    updated = np.ones(T, bool)
    rows = cloud_rows(truth, vo, best, poses, np.full(T, 3.5), resampled, updated, every_m=10.0)

    assert [r["frame"] for r in rows] == [0, 10, 20]
    r = rows[1]  # t = 10: a = 1
    np.testing.assert_allclose(r["cloud_rms_m"], math.sqrt(2.0))
    np.testing.assert_allclose(r["heading_std_deg"], math.degrees(0.1), rtol=1e-9)
    np.testing.assert_allclose(r["nearest_particle_m"], 1.0)  # the two corners at y = 0
    np.testing.assert_allclose(r["mean_error_m"], 1.0)
    np.testing.assert_allclose(r["best_error_m"], math.hypot(1.0, 2.0))
    np.testing.assert_allclose(r["vo_error_m"], 0.5)
    assert (r["resampled"], r["updates"]) == (1, 10)  # frames 1-10
    assert (rows[2]["resampled"], rows[2]["updates"]) == (2, 10)  # frames 11-20


def test_cloud_rows_zoom_in_from_the_approach_and_count_the_near_weight():
    # the cloud above; from frame 14 on a row every 2 m; weights 0.4 / 0.3 / 0.2 / 0.1
    truth, poses, resampled = _square_cloud()
    log_w = np.broadcast_to(np.log([0.4, 0.3, 0.2, 0.1]), (T, 4))
    rows = cloud_rows(truth, truth, truth, poses, np.full(T, 3.5), resampled, np.ones(T, bool),
                      every_m=10.0, log_w=log_w, zoom_from=14, zoom_m=2.0)

    assert [r["frame"] for r in rows] == [0, 10, 14, 16, 18, 20]
    # t = 10: the corners (1, -1) and (-1, -1) lie exactly 1 m from the truth, the others
    # sqrt(1 + 4) m; t = 0: every particle 1 m off (a = 0)
    assert [r["within_1m"] for r in rows[:2]] == [4, 2]
    np.testing.assert_allclose(rows[1]["weight_within_1m"], 0.3 + 0.1)
    np.testing.assert_allclose(rows[0]["weight_within_1m"], 1.0)
    assert rows[-1]["within_1m"] == 0 and rows[-1]["weight_within_1m"] == 0.0
    # the nearest at t = 10 is the first corner at y = 0, particle 1 (heading pi - 0.1 against
    # the truth's 0)
    np.testing.assert_allclose(rows[1]["nearest_heading_deg"], math.degrees(math.pi - 0.1))
    assert [(r["resampled"], r["updates"]) for r in rows[2:]] == [(2, 4), (0, 2), (0, 2), (0, 2)]
    assert np.isnan(cloud_rows(truth, truth, truth, poses, np.full(T, 3.5), resampled,
                               np.ones(T, bool), every_m=10.0)[0]["weight_within_1m"])


def test_simulated_loop_takes_the_vo_and_noise_scales_as_loop_closure_does(monkeypatch) -> None:
    """--vo-scale, --vo-failures and --noise-scale reach the simulation and the filter's config
    as in ``loop_closure``, so that ``loop_cloud`` and ``revisit_terms`` repeat its runs."""
    seen = {}

    class Simulated(Exception):
        pass

    def simulate(who):
        def record(file_, length, seed, config, course, max_frames, *rest, vo_noise=None):
            seen[who] = (config.motion, rest[-1] if rest else vo_noise)
            raise Simulated
        return record

    flags = ["--course", "arroyo-a", "--vo-scale", "0.3", "--noise-scale", "2",
             "--vo-failures", "0.5"]
    monkeypatch.setattr(lc, "simulate_loop", simulate("loop_closure"))
    with pytest.raises(Simulated):
        lc.main(["--circles", "30", "--particles", "8", "--proposals", "motion", "--seeds", "1"]
                + flags)
    monkeypatch.setattr(loop_cloud, "simulate_loop", simulate("loop_cloud"))
    ap = argparse.ArgumentParser()
    loop_cloud.add_loop_arguments(ap)
    with pytest.raises(Simulated):
        loop_cloud.simulated_loop(ap.parse_args(["--circle", "30", "--seed", "1"] + flags))
    assert seen["loop_cloud"] == seen["loop_closure"]
    motion, noise = seen["loop_cloud"]
    assert noise.failure_rate > 0 and noise.alpha_theta_d > 0
    assert motion != lc.layered_config(None, "arroyo-a", []).motion
