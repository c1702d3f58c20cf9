"""Motion model (eqs. 1-3): sample moments and the log density against SciPy."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from gslam_jax.rbpf.motion import MotionParams, apply_motion, log_density, sample_motion

PARAMS = MotionParams(alpha_d=0.1, alpha_theta_d=0.02, alpha_theta=0.2)


def test_sample_mean_and_covariance_match_eqs_1_to_3():
    pose = jnp.array([1.0, -2.0, 0.7])
    u = jnp.array([0.8, 0.3, 0.25])
    n = 400_000
    x = np.asarray(sample_motion(jax.random.key(0), jnp.broadcast_to(pose, (n, 3)), u, PARAMS), np.float64)
    c, s = np.cos(0.7), np.sin(0.7)
    delta = np.array([c * 0.8 - s * 0.3, s * 0.8 + c * 0.3])
    dist = np.hypot(0.8, 0.3)
    sigma_d = 0.1 * dist
    sigma_t = 0.02 * dist + 0.2 * 0.25
    np.testing.assert_allclose(x[:, :2].mean(0), [1.0 + delta[0], -2.0 + delta[1]], atol=2e-3)
    assert x[:, 2].mean() == pytest.approx(0.95, abs=2e-3)
    direction = delta / dist
    expected_cov = sigma_d**2 * np.outer(direction, direction)  # 1-D along the translation
    np.testing.assert_allclose(np.cov(x[:, :2].T), expected_cov, atol=1e-4)
    assert x[:, 2].std() == pytest.approx(sigma_t, rel=1e-2)
    # no noise across the direction of travel
    across = (x[:, :2] - pose[:2]) @ np.array([-direction[1], direction[0]])
    assert np.abs(across).max() < 1e-5


def test_log_density_matches_scipy_normals():
    pose = jnp.array([0.0, 0.0, 0.3])
    u = jnp.array([1.0, 0.0, 0.1])
    eps = jnp.array([0.7, -1.3, 0.4])  # the cross-track draw is unused at alpha_cross = 0
    new = apply_motion(pose, u, eps, PARAMS)
    sigma_d = 0.1
    sigma_t = 0.02 + 0.2 * 0.1
    ref = stats.norm(1.0, sigma_d).logpdf(1.0 + sigma_d * 0.7) + stats.norm(0, sigma_t).logpdf(-1.3 * sigma_t)
    assert float(log_density(new, pose, u, PARAMS)) == pytest.approx(ref, rel=1e-5)


def test_samples_are_differentiable_in_the_alphas():
    pose = jnp.zeros(3)
    u = jnp.array([1.0, 0.0, 0.0])
    eps = jnp.array([1.0, 1.0, 1.0])
    g = jax.grad(lambda a: apply_motion(pose, u, eps, MotionParams(a, 0.02, 0.2))[0])(0.1)
    assert float(g) == pytest.approx(1.0)  # x = 1 + alpha_d * eps along track


def test_cross_track_noise_matches_a_full_covariance():
    """With alpha_cross > 0 the position spreads across Delta d with std alpha_cross |d|,
    independent of the along-track and heading noise."""
    params = PARAMS._replace(alpha_cross=0.05)
    pose = jnp.array([1.0, -2.0, 0.7])
    u = jnp.array([0.8, 0.3, 0.25])
    x = np.asarray(sample_motion(jax.random.key(1), jnp.broadcast_to(pose, (400_000, 3)), u,
                                 params), np.float64)
    c, s = np.cos(0.7), np.sin(0.7)
    delta = np.array([c * 0.8 - s * 0.3, s * 0.8 + c * 0.3])
    dist = np.hypot(0.8, 0.3)
    along, normal = delta / dist, np.array([-delta[1], delta[0]]) / dist
    expected = ((0.1 * dist) ** 2 * np.outer(along, along)
                + (0.05 * dist) ** 2 * np.outer(normal, normal))
    np.testing.assert_allclose(np.cov(x[:, :2].T), expected, atol=1e-4)
    assert abs(np.corrcoef((x[:, :2] - np.asarray(pose[:2])) @ normal, x[:, 2])[0, 1]) < 0.01


def test_log_density_with_cross_track_matches_scipy():
    params = PARAMS._replace(alpha_cross=0.05)
    pose = jnp.array([0.5, 0.2, 1.1])
    u = jnp.array([0.9, -0.2, 0.1])
    new = jnp.array([0.5 + 0.2, 0.2 + 0.95, 1.1 + 0.13])
    c, s = np.cos(1.1), np.sin(1.1)
    delta = np.array([c * 0.9 + s * 0.2, s * 0.9 - c * 0.2])
    dist = np.hypot(0.9, 0.2)
    along, normal = delta / dist, np.array([-delta[1], delta[0]]) / dist
    step = np.array([0.2, 0.95])
    ref = (stats.norm(dist, 0.1 * dist).logpdf(step @ along)
           + stats.norm(0, 0.05 * dist).logpdf(step @ normal)
           + stats.norm(0.1, 0.02 * dist + 0.2 * 0.1).logpdf(0.13))
    assert float(log_density(new, pose, u, params)) == pytest.approx(ref, rel=1e-5)


def test_zero_cross_track_noise_is_the_papers_model():
    """alpha_cross = 0 moves a particle exactly as the two-draw model does."""
    pose = jnp.array([[0.3, -0.1, 0.4]])
    u = jnp.array([0.7, 0.1, -0.05])
    a = apply_motion(pose, u, jnp.array([[0.3, -1.1, 2.5]]), PARAMS)
    b = apply_motion(pose, u, jnp.array([[0.3, -1.1, -0.7]]), PARAMS)
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
