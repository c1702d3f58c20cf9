"""Cell statistics against independent references (SciPy, quadrature, Monte Carlo)."""

import jax.numpy as jnp
import numpy as np
import pytest
from jax import enable_x64
from scipy import integrate, special, stats

from gslam_jax.rbpf import cells


def _pred64(k, S, kp, Sp):
    with enable_x64(True):
        return float(cells.log_predictive(np.float64(k), np.float64(S), np.float64(kp), np.float64(Sp)))


@pytest.mark.parametrize("k,kp,vp", [(1, 1, 0.5), (4, 9, 0.02), (12, 3, 1.7), (30, 60, 0.1)])
def test_eq18_is_a_density_in_v(k, kp, vp):
    Sp = kp * vp
    total, err = integrate.quad(lambda v: np.exp(_pred64(k, k * v, kp, Sp)), 0, np.inf, limit=200)
    assert total == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("k,kp,vp", [(3, 5, 0.3), (10, 20, 0.05)])
def test_eq18_matches_monte_carlo_of_the_generative_model(k, kp, vp):
    """h ~ Gamma(k'/2, rate k'v'/2), then v ~ Gamma(k/2, rate h k/2) (eqs. 9, 15)."""
    rng = np.random.default_rng(0)
    n = 400_000
    h = rng.gamma(kp / 2, 2 / (kp * vp), n)
    v = rng.gamma(k / 2, 2 / (h * k))
    for q in (0.1, 0.5, 0.9):
        a = np.quantile(v, q)
        mass, _ = integrate.quad(lambda x: np.exp(_pred64(k, k * x, kp, kp * vp)), 0, a, limit=200)
        assert mass == pytest.approx(q, abs=0.005)


def test_eq9_matches_scipy_gamma():
    rng = np.random.default_rng(1)
    v = rng.gamma(2, 0.1, 50)
    k = rng.integers(1, 40, 50).astype(float)
    h = rng.gamma(2, 5, 50)
    with enable_x64(True):
        ours = np.asarray(cells.log_likelihood_given_precision(v, k, h))
    ref = stats.gamma(a=k / 2, scale=2 / (h * k)).logpdf(v)
    np.testing.assert_allclose(ours, ref, rtol=1e-10)


def test_pooled_statistics_are_order_independent():
    rng = np.random.default_rng(2)
    z = rng.normal(0.3, 0.2, 97)
    chunks = np.split(rng.permutation(z), [10, 40, 41, 80])
    merged = np.zeros(3)
    for c in reversed(chunks):
        merged = cells.merge_stats(merged, cells.stats_from_points(c))
    np.testing.assert_allclose(merged, cells.stats_from_points(z))
    k, S = cells.obs_from_stats(merged)
    assert k == 96
    assert S == pytest.approx(np.sum((z - z.mean()) ** 2), rel=1e-10)


def test_map_update_is_order_independent():
    rng = np.random.default_rng(3)
    obs = [(rng.integers(1, 20), rng.gamma(2, 0.1)) for _ in range(6)]
    def apply(order):
        k, S = 0.0, 0.0
        for i in order:
            k, S = cells.conjugate_update(k, S, *obs[i])
        return k, S
    a, b = apply(range(6)), apply(rng.permutation(6))
    assert a[0] == b[0] and a[1] == pytest.approx(b[1], rel=1e-12)


def test_obs_from_stats_needs_two_points_and_floors_variance():
    stats_ = np.array([[1, 0.5, 0.25], [3, 3.0, 3.0], [0, 0, 0]])
    obs = cells.obs_from_stats(stats_, min_variance=1e-4)
    np.testing.assert_array_equal(obs[0], [0, 0])
    np.testing.assert_allclose(obs[1], [2, 2e-4])  # identical heights: S floored at k * 1e-4
    np.testing.assert_array_equal(obs[2], [0, 0])


def test_refine_obs_on_device_matches_obs_from_stats():
    """Floor, weight and point threshold applied on the device to raw observations equal the
    host's float64 observations with the same settings (float32 tolerance)."""
    rng = np.random.default_rng(5)
    n = rng.integers(0, 9, 400).astype(float)
    z = [rng.normal(1.0, rng.choice([0.0, 1e-4, 0.1]), int(k)) for k in n]
    stats_ = np.stack([cells.stats_from_points(v) for v in z])
    raw = jnp.asarray(cells.obs_from_stats(stats_, 0.0), jnp.float32)
    for mv, w, mp in [(1e-6, 1.0, 2), (1e-3, 0.4, 3), (1e-2, 2.0, 5)]:
        want = cells.obs_from_stats(stats_, mv, w, mp)
        got = np.asarray(cells.refine_obs(raw, mv, w, float(mp)))
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-9)
        assert np.all((want[:, 0] > 0) == (n >= mp))
    with pytest.raises(ValueError, match="min_points"):
        cells.obs_from_stats(stats_, 1e-6, 1.0, 1)


def test_lgamma_table_and_stirling_match_scipy():
    k = np.concatenate([np.arange(1, 400), np.arange(16000, 16800), [1e5, 3e6]]).astype(np.float32)
    ours = np.asarray(cells.lgamma_half(k), np.float64)
    ref = special.gammaln(k.astype(np.float64) / 2)
    np.testing.assert_allclose(ours, ref, rtol=2e-6, atol=2e-6)


def test_integer_fast_path_matches_reference_eq26():
    rng = np.random.default_rng(4)
    k = rng.integers(1, 300, 1000).astype(np.float32)
    kp = rng.integers(1, 20000, 1000).astype(np.float32)
    S = (k * rng.gamma(2, 0.01, 1000)).astype(np.float32)
    Sp = (kp * rng.gamma(2, 0.01, 1000)).astype(np.float32)
    with enable_x64(True):
        ref = np.asarray(cells.log_predictive(*(x.astype(np.float64) for x in (k, S, kp, Sp))))
    fast = np.asarray(cells.log_predictive_integer(k, S, kp, Sp))
    # The naive float32 form is off by up to 2e-2 here (terms of size k'' log S'' ~ 1e4).
    np.testing.assert_allclose(fast, ref, atol=5e-4)


def test_expected_std_matches_monte_carlo():
    k, S = 7.0, 7 * 0.04
    rng = np.random.default_rng(5)
    h = rng.gamma(k / 2, 2 / S, 1_000_000)
    assert float(cells.expected_std(k, S)) == pytest.approx(np.mean(h ** -0.5), rel=3e-3)
    assert np.isnan(float(cells.expected_std(0.0, 0.0)))


@pytest.mark.parametrize("shared_log_v", [False, True])
def test_float32_eq26_when_one_variance_dwarfs_the_other(shared_log_v):
    """A flat prior cell (S' floored at k' * 1e-6) under a tall observation, and the reverse:
    S / S'' is within float32 rounding of 1, where log1p(-S / S'') loses every digit."""
    rng = np.random.default_rng(5)
    k = rng.integers(1, 40, 400).astype(np.float32)
    kp = rng.integers(1, 400, 400).astype(np.float32)
    tall, flat = rng.gamma(2, 0.05, 400), 1e-6 * rng.uniform(1, 3, 400)
    for v, vp in ((tall, flat), (flat, tall)):
        S, Sp = (k * v).astype(np.float32), (kp * vp).astype(np.float32)
        with enable_x64(True):
            ref = np.asarray(cells.log_predictive(*(x.astype(np.float64) for x in (k, S, kp, Sp))))
        log_v = cells.log_v_obs(k, S) if shared_log_v else None
        got = cells.log_predictive_integer(k, S, kp, Sp, log_v=log_v)
        np.testing.assert_allclose(np.asarray(got), ref, atol=5e-4, rtol=1e-6)
