"""The observation-informed proposal (rbpf/proposal.py): its Gaussian fit, its importance
weights against brute-force integration, its covariance against Monte Carlo of the motion model,
and the filter with it."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from gslam_jax.rbpf import proposal
from gslam_jax.rbpf.motion import MotionParams, apply_motion


def _quadratic_score(g: np.ndarray, centre: np.ndarray, precision: np.ndarray) -> np.ndarray:
    """A synthetic log score in whitened coordinates: -(g - c)^T A (g - c) / 2."""
    d = g - centre
    return -0.5 * np.einsum("...a,ab,...b->...", d, precision, d)


def _fit(centre: np.ndarray, precision: np.ndarray, phi: float, points: int = 3,
         stages: int = 2):
    """The staged fit of one particle whose score is ``_quadratic_score``."""
    def score(g):
        return jnp.asarray(_quadratic_score(np.asarray(g), centre, precision), jnp.float32)

    mu, q_chol, got = proposal.fit_proposal(score, 1, points, 2.0, stages,
                                            lambda centre_scores: jnp.float32(phi))
    assert float(got) == pytest.approx(phi)
    return mu, q_chol


@pytest.mark.parametrize("precision", [np.diag([4.0, 9.0, 25.0]), np.diag([0.0, 9.0, 25.0])])
def test_weights_are_exact_importance_weights_of_the_tempered_target(precision):
    """E_q[exp(correction + phi log lambda)] is the target's normaliser
    Z = int N(g; 0, I) lambda(g)^phi dg, whatever Gaussian the fit chose; Z by brute-force
    integration on a fine grid (and in closed form), the expectation by Monte Carlo."""
    centre = np.array([0.8, -0.5, 0.3])
    phi = 0.7
    mu, q_chol = _fit(centre, precision, phi)
    z = jax.random.normal(jax.random.key(0), (200_000, 3))
    g = mu + z @ q_chol[0].T
    eye = jnp.broadcast_to(jnp.eye(3), (g.shape[0], 3, 3))
    correction = (proposal._log_normal(g, jnp.zeros_like(g), eye)
                  - proposal._log_normal(g, jnp.broadcast_to(mu, g.shape),
                                         jnp.broadcast_to(q_chol, eye.shape)))
    w = np.exp(np.asarray(correction, np.float64)
               + phi * _quadratic_score(np.asarray(g, np.float64), centre, precision))
    axis = np.linspace(-7, 7, 141)
    G = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    integrand = stats.multivariate_normal(np.zeros(3), np.eye(3)).pdf(G) * np.exp(
        phi * _quadratic_score(G, centre, precision))
    brute = integrand.sum() * (axis[1] - axis[0]) ** 3
    A = phi * precision
    closed = math.exp(-0.5 * centre @ A @ np.linalg.solve(np.eye(3) + A, centre)) / math.sqrt(
        np.linalg.det(np.eye(3) + A))
    assert brute == pytest.approx(closed, rel=1e-4)
    assert w.mean() == pytest.approx(closed, rel=0.02)


def test_a_flat_direction_follows_the_prior_and_a_peaked_one_the_score():
    """Score flat along axis 0 (a straight road's along-track), sharp along axes 1 and 2."""
    precision = np.diag([0.0, 50.0, 50.0])
    mu, q_chol = _fit(np.array([0.0, 0.6, -0.4]), precision, 1.0)
    Q = np.asarray(q_chol[0] @ q_chol[0].T)
    assert abs(float(mu[0, 0])) < 1e-3 and 0.8 < Q[0, 0] < 1.2  # the prior N(0, 1)
    # the target's width: precision 50 + 1 (the score and the prior)
    np.testing.assert_allclose([Q[1, 1], Q[2, 2]], 1 / 51, rtol=0.05)
    # the target's mean, between the first grid's points: 50 c / 51
    np.testing.assert_allclose(mu[0, 1:], np.array([0.6, -0.4]) * 50 / 51, atol=1e-3)


def test_the_grid_starts_at_the_prior_mean():
    grid, spacing = proposal.candidate_grid(3, 2.0)
    assert grid.shape == (27, 3) and spacing == 2.0
    np.testing.assert_array_equal(grid[0], 0.0)
    grid, spacing = proposal.candidate_grid(1, 2.0)
    assert grid.shape == (1, 3) and spacing == 0.0


def test_accumulated_covariance_matches_monte_carlo_of_the_motion_model():
    params = MotionParams(0.05, 0.01, 0.05)
    controls = jnp.asarray(np.tile([0.3, 0.0, 0.02], (20, 1)), jnp.float32)
    pose = jnp.zeros(3)
    cov = jnp.zeros((3, 3))
    for u in controls:
        pose, cov = proposal.propagate_mean(pose, cov, u, params)
    n = 100_000
    samples = jnp.zeros((n, 3))
    for t, u in enumerate(controls):
        eps = jax.random.normal(jax.random.key(t), (n, 2))
        samples = apply_motion(samples, u, eps, params)
    emp = np.cov(np.asarray(samples, np.float64).T)
    np.testing.assert_allclose(np.asarray(samples).mean(0), np.asarray(pose), atol=3e-3)
    np.testing.assert_allclose(np.asarray(cov), emp, rtol=0.08, atol=2e-5)
