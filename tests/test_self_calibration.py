"""experiments/self_calibration.py: the alphas fitted to a reference path in place of the ground
truth are ``gslam fit-motion``'s with the ground truth as that path, and none with the VO's own
path (which explains its increments exactly)."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic import truth_and_controls

from experiments import self_calibration as S
from experiments.common import alphas_of, with_alphas
from gslam_jax.config import Config
from gslam_jax.run import Run
from gslam_jax.tuning.motion_fit import fit_run


@pytest.fixture(scope="module")
def run() -> Run:
    """A loop whose VO errs along-track by 5 % and in heading by 0.02 rad per metre."""
    gt, u = truth_and_controls("loop", 200)
    rng = np.random.default_rng(3)
    noisy = u.copy()
    noisy[:, 0] *= 1 + 0.05 * rng.standard_normal(len(u))
    noisy[:, 2] += 0.02 * u[:, 0] * rng.standard_normal(len(u))
    return Run(controls=noisy, obs_index=np.full(len(u), -1), local_maps=np.zeros((0, 8, 8, 3)),
               resolution=0.2, timestamps=np.arange(len(u)) * 0.1, ground_truth=gt,
               vo_failed=np.zeros(len(u), bool), initial_pose=np.zeros(3))


def test_the_ground_truth_as_reference_gives_fit_motions_alphas(run):
    fit = fit_run(run)
    got = S.self_fit(run, run.ground_truth)
    np.testing.assert_allclose(got[:2], (fit.alpha_d, fit.alpha_theta_d), rtol=1e-12)
    assert got[0] == pytest.approx(0.05, rel=0.3)
    assert got[1] == pytest.approx(0.02, rel=0.3)


def test_the_vos_own_path_explains_its_increments(run):
    a_d, a_td, a_t = S.self_fit(run, run.vo_poses())
    assert a_d < 1e-6 and a_td < 1e-6
    assert a_t == S.MIN_ALPHA_THETA  # clipped above 0: a turn in place keeps some noise


def test_with_alphas_sets_the_three_and_nothing_else():
    config = Config()
    got = with_alphas(config, (0.1, 0.2, 0.3))
    assert alphas_of(got) == (0.1, 0.2, 0.3)
    assert got.motion.alpha_cross == config.motion.alpha_cross and got.filter == config.filter
