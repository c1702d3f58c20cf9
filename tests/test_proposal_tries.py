"""Importance resampling within each particle (``[filter] proposal_tries``,
``proposal.draw_tries``): the weight is an unbiased estimate of the tempered target's
normaliser and the kept pose with it is properly weighted (Monte Carlo against brute-force
integration); in the filter the weights are the mean of the tries' eq. 26 scores (brute force,
SciPy) and the kept pose is the one the uniform picks."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats
from scipy.special import logsumexp

from gslam_jax.config import Config, ConfigError, layered_config
from gslam_jax.rbpf import kernel, proposal
from test_proposal import _brute_log_lambda, _small_case

CENTRE = np.array([0.8, -0.5, 0.3])
PRECISION = np.diag([4.0, 9.0, 0.0])  # the third direction flat: the prior alone there
PHI = 0.7


def _score(g: jax.Array) -> jax.Array:
    d = g - jnp.asarray(CENTRE, jnp.float32)
    return -0.5 * jnp.einsum("...a,ab,...b->...", d, jnp.asarray(PRECISION, jnp.float32), d)


def _brute_target() -> tuple[float, np.ndarray]:
    """Normaliser Z = int N(g; 0, I) lambda(g)^phi dg and the target's mean, on a fine grid."""
    axis = np.linspace(-7, 7, 141)
    G = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    d = G - CENTRE
    f = stats.multivariate_normal(np.zeros(3), np.eye(3)).pdf(G) * np.exp(
        -0.5 * PHI * np.einsum("na,ab,nb->n", d, PRECISION, d))
    Z = f.sum() * (axis[1] - axis[0]) ** 3
    return Z, (G * f[:, None]).sum(0) / f.sum()


@pytest.mark.parametrize("fitted", [False, True], ids=["from-the-prior", "from-the-fit"])
@pytest.mark.parametrize("tries", [1, 4])
def test_the_weight_is_unbiased_and_the_kept_draw_properly_weighted(fitted, tries):
    J = 200_000
    if fitted:  # a Gaussian fitted to a different score: the weights must correct any proposal
        mu, L, _ = proposal.fit_proposal(lambda g: 0.5 * _score(g), 1, 3, 2.0, 2,
                                         lambda lam, p: jnp.float32(PHI))
        mu, L = jnp.broadcast_to(mu, (J, 3)), jnp.broadcast_to(L, (J, 3, 3))
    else:
        mu, L = jnp.zeros((J, 3)), jnp.broadcast_to(jnp.eye(3), (J, 3, 3))
    k_z, k_u = jax.random.split(jax.random.key(0))
    z = jax.random.normal(k_z, (J, tries, 3))
    u = jax.random.uniform(k_u, (J,))
    g, correction, phi = proposal.draw_tries(_score, mu, L, z, u, None,
                                             jnp.float32(PHI))
    assert float(phi) == pytest.approx(PHI)
    # the weight the update forms: phi log lambda at the kept pose plus the correction
    log_w = np.asarray(correction, np.float64) + PHI * np.asarray(_score(g), np.float64)
    w = np.exp(log_w)
    Z, mean = _brute_target()
    # within 4 standard errors of the Monte Carlo mean (and the grid's 0.1 %)
    assert abs(w.mean() - Z) < 4 * w.std() / math.sqrt(J) + 1e-3 * Z
    weighted = (w[:, None] * np.asarray(g)).sum(0) / w.sum()
    se = np.sqrt(((w / w.mean())[:, None] ** 2 * (np.asarray(g) - weighted) ** 2).mean(0) / J)
    assert np.all(np.abs(weighted - mean) < 4 * se + 1e-3)


def test_more_tries_give_steadier_weights():
    J = 20_000
    spread = []
    for tries in (1, 16):
        z = jax.random.normal(jax.random.key(1), (J, tries, 3))
        u = jax.random.uniform(jax.random.key(2), (J,))
        g, correction, _ = proposal.draw_tries(
            _score, jnp.zeros((J, 3)), jnp.broadcast_to(jnp.eye(3), (J, 3, 3)), z, u, None,
            jnp.float32(PHI))
        spread.append(np.std(np.asarray(correction) + PHI * np.asarray(_score(g))))
    assert spread[1] < 0.5 * spread[0]


def test_in_the_filter_the_weight_is_the_mean_of_the_tries_eq_26_scores():
    """With the prior as the proposal (proposal_points = 1) and the paper's fixed beta, each
    particle's weight is multiplied by the mean over its tries of lambda (eq. 26 with eq. 30,
    brute force at every try's pose) and its pose is the try the uniform picks by inverse CDF
    of lambda."""
    tries = 5
    cfg, state, local, (k, S) = _small_case(points=1)
    cfg = cfg._replace(proposal_tries=tries).validate()
    J = cfg.num_particles
    noise = kernel.update_noise(jax.random.key(7), cfg)
    single = kernel.update_noise(jax.random.key(7), cfg._replace(proposal_tries=1))
    np.testing.assert_array_equal(noise.proposal_z[:, 0], single.proposal_z)  # first try
    params = kernel.FilterParams()
    new, info = kernel.update(state, local, noise.unknown_u, params, cfg, noise.proposal_z,
                              proposal_u=noise.proposal_u)
    chol = np.linalg.cholesky(np.asarray(state.prior_cov, np.float64)
                              + np.diag(proposal.JITTER))
    poses = (np.asarray(state.pose, np.float64)[:, None, :]
             + np.einsum("jab,jmb->jma", chol, np.asarray(noise.proposal_z, np.float64)))
    lam = np.array([[_brute_log_lambda(p, np.asarray(local), k, S, cfg,
                                       float(params.beta_prev)) for p in row] for row in poses])
    unnorm = np.asarray(state.log_w, np.float64) + logsumexp(lam, axis=1) - math.log(tries)
    np.testing.assert_allclose(new.log_w, unnorm - logsumexp(unnorm), atol=2e-3)
    cdf = np.cumsum(np.exp(lam - logsumexp(lam, axis=1, keepdims=True)), axis=1)
    kept = (cdf < np.asarray(noise.proposal_u)[:, None]).sum(1)
    np.testing.assert_allclose(new.pose, poses[np.arange(J), kept], atol=1e-5)
    assert float(info.exponent) == 1.0


@pytest.mark.parametrize("settings,field", [
    ({"proposal_tries": 4}, "proposal_tries"),  # the motion proposal has no tries
    ({"proposal": "informed", "proposal_tries": 4, "proposal_cell_stride": 2},
     "proposal_tries"),
    ({"proposal": "informed", "proposal_tries": 0}, "proposal_tries"),
])
def test_tries_need_the_informed_proposal_scoring_every_cell(settings, field):
    with pytest.raises(ConfigError, match=field):
        layered_config(None, overrides=[f"filter.{k}={v}" for k, v in settings.items()])
    assert Config().filter.proposal_tries == 1
