"""The motion noise fitted to the filter's evidence (tuning/evidence_fit.py, `gslam fit-motion
--evidence`): the ladder against plain filter runs, its choice, its refusals, the CLI."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from synthetic import make_run

from gslam_jax.config import Config, FilterSection, MapSection, MotionSection
from gslam_jax.driver import slam
from gslam_jax.tuning.evidence_fit import fit_noise_scale
from gslam_jax.tuning.space import ALPHA_NAMES, SearchError
from gslam_jax.vo.localmap import LocalMapParams

LM = LocalMapParams(resolution=0.16, max_range=2.5, travel=1.0)
CONFIG = Config(filter=FilterSection(particles=16, unknown_cells="ignore"),
                map=MapSection(margin=3.0))


@pytest.fixture(scope="module")
def drifting_run():
    """60 frames whose VO turns 0.02 rad a frame too far (its evidence peaks near the default
    alphas: 0.8x from below, 1.6x from above on the test's ladders)."""
    run, _ = make_run(seed=1, steps=60, drift=0.02, params=LM)
    return run


def _scaled(config: Config, factor: float) -> Config:
    m = config.motion
    return dataclasses.replace(config, motion=dataclasses.replace(
        m, **{n: getattr(m, n) * factor for n in ALPHA_NAMES}))


def test_the_ladder_is_each_runs_evidence_under_fixed_tempering(drifting_run):
    """Each factor's log evidence is the sum of a plain filter run's log mean weight
    increments with the alphas times that factor and the paper's fixed beta (slam.run_slam,
    not the batched evaluation), and the best factor is the highest."""
    factors = (0.5, 2.0, 8.0)
    fit = fit_noise_scale(drifting_run, CONFIG, factors, seeds=(3,))
    cfg = dataclasses.replace(CONFIG, filter=dataclasses.replace(CONFIG.filter, seed=3,
                                                                 tempering="fixed"))
    want = [float(np.sum(slam.run_slam(drifting_run, _scaled(cfg, f)).log_lik)) for f in factors]
    np.testing.assert_allclose(fit.log_evidence, want, rtol=1e-4)
    best = int(np.argmax(want))
    assert fit.factor == factors[best]
    assert fit.on_edge == (best in (0, len(factors) - 1)) and not fit.kept
    fitted = fit.config(CONFIG)
    for n in ALPHA_NAMES:
        assert getattr(fitted.motion, n) == pytest.approx(getattr(CONFIG.motion, n) * fit.factor)
    assert fitted.filter == CONFIG.filter  # the config's own tempering is kept


def test_a_noise_too_narrow_for_the_vo_is_widened_and_one_too_wide_narrowed(drifting_run):
    """From alphas ten times too narrow the evidence moves up, and from alphas a hundred times
    too wide it moves down, to the same neighbourhood (within 4x of each other)."""
    narrow = _scaled(CONFIG, 0.1)
    wide = _scaled(CONFIG, 100.0)
    factors = tuple(2.0 ** k for k in range(-8, 9))
    up = fit_noise_scale(drifting_run, narrow, factors, seeds=(0,))
    down = fit_noise_scale(drifting_run, wide, factors, seeds=(0,))
    assert up.factor > 1.0 and down.factor < 1.0
    assert not up.on_edge and not down.on_edge
    ratio = (0.1 * up.factor) / (100.0 * down.factor)
    assert 0.25 <= ratio <= 4.0, (up.factor, down.factor)


def test_a_noise_that_carries_particles_off_the_map_scores_nan_and_is_never_chosen(
        drifting_run):
    # three rungs, as the ladder test's: one compiled batch for both
    fit = fit_noise_scale(drifting_run, CONFIG, (1.0, 1e4, 1e5), seeds=(0,))
    assert np.isfinite(fit.log_evidence[0]) and np.all(np.isnan(fit.log_evidence[1:]))
    assert fit.factor == 1.0


@pytest.mark.parametrize("factors,match", [((), "positive and finite"),
                                           ((0.0, 1.0), "positive and finite"),
                                           ((float("nan"),), "positive and finite")])
def test_bad_ladders_are_refused(drifting_run, factors, match):
    with pytest.raises(SearchError, match=match):
        fit_noise_scale(drifting_run, CONFIG, factors)


def test_no_noise_to_scale_and_no_seeds_are_refused(drifting_run):
    still = dataclasses.replace(CONFIG, motion=MotionSection(0.0, 0.0, 0.0, 0.0))
    with pytest.raises(SearchError, match="every alpha is 0"):
        fit_noise_scale(drifting_run, still, (1.0, 2.0))
    with pytest.raises(SearchError, match="seeds"):
        fit_noise_scale(drifting_run, CONFIG, (1.0,), seeds=())


def test_cli_writes_the_fitted_config_without_ground_truth(tmp_path, drifting_run, capsys):
    from gslam_jax.app.cli import main
    from gslam_jax.config import load_config
    from gslam_jax.run import save_run

    blind = drifting_run._replace(ground_truth=None)
    path, out = tmp_path / "r.npz", tmp_path / "fitted.toml"
    save_run(path, blind)
    argv = ["fit-motion", str(path), "--evidence", "--factors", "0.5", "4", "32",
            "--evidence-seeds", "0", "1",
            "--set", "filter.particles=16", "--set", "map.margin=3.0"]
    assert main([*argv, "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "<- chosen" in text and "log evidence" in text
    fitted = load_config(out)
    factor = fitted.motion.alpha_d / MotionSection().alpha_d
    assert factor == pytest.approx(min((0.5, 4.0, 32.0), key=lambda f: abs(f - factor)))
    assert fitted.motion.alpha_theta == pytest.approx(MotionSection().alpha_theta * factor)
    assert main(["fit-motion", str(path), "--factors", "2"]) == 2  # needs --evidence
    assert "--evidence" in capsys.readouterr().err
    assert main(["fit-motion", str(path), "--evidence", "--window", "3"]) == 2


def test_cli_notes_that_the_fit_is_not_for_stereo(tmp_path, drifting_run, capsys):
    from gslam_jax.app.cli import main
    from gslam_jax.run import save_run

    path = tmp_path / "r.npz"
    for sensor, noted in (("stereo", True), ("points", False)):
        save_run(path, drifting_run._replace(sensor=sensor))
        assert main(["fit-motion", str(path), "--evidence", "--factors", "1", "2", "4",
                     "--evidence-seeds", "0", "--set", "filter.particles=16",
                     "--set", "map.margin=3.0"]) == 0
        assert ("is for the point sensor" in capsys.readouterr().out) == noted


def test_the_experiment_runs_the_fitted_noise_it_reports(tmp_path, drifting_run, monkeypatch):
    """experiments/evidence_noise.py: the fitted scale is the given scale times the ladder's
    factor, and the fitted run is a plain run at those alphas (the same RMS)."""
    import json
    import sys

    from experiments import evidence_noise
    from experiments.proposal_compare import case_row
    from gslam_jax.config import apply_overrides
    from gslam_jax.run import save_run

    path, out = tmp_path / "r.npz", tmp_path / "rows.json"
    save_run(path, drifting_run)
    monkeypatch.setattr(sys, "argv", [
        "evidence_noise", "--runs", str(path), "--noise-scale", "4", "--seeds", "1",
        "--factors", "0.25", "1", "4", "--evidence-seeds", "0", "--set", "filter.particles=16",
        "--set", "map.margin=3.0", "--json", str(out)])
    assert evidence_noise.main() == 0
    (row,) = [json.loads(line) for line in out.read_text().splitlines()]
    assert row["fitted_scale"] == pytest.approx(4 * row["factor"])
    assert row["factor"] in (0.25, 1.0, 4.0)
    config = apply_overrides(Config(), ["filter.particles=16", "map.margin=3.0"])
    want = case_row(str(path), drifting_run, config, row["fitted_scale"], "motion", 1)
    assert row["fitted_rms_m"] == pytest.approx(want["slam_rms_m"], rel=1e-6)


def test_a_log_without_local_maps_keeps_the_given_noise(drifting_run):
    """No local map, no evidence about the noise: every rung scores 0, and the given alphas
    (factor 1) are kept rather than the ladder's first rung."""
    blind = drifting_run._replace(obs_index=np.full(drifting_run.num_frames, -1))
    fit = fit_noise_scale(blind, CONFIG, (0.5, 1.0, 2.0), seeds=(0,))
    np.testing.assert_array_equal(fit.log_evidence, 0.0)
    assert fit.factor == 1.0 and not fit.on_edge and fit.kept  # the argmax (rung 1) only ties
    assert fit.config(CONFIG).motion == CONFIG.motion
