"""Adaptive tempering (issue 16): the exponent against a brute-force grid search of the
conditional ESS, the tiled reference's independent root finder, and the filter's call site."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gslam_jax import rbpf as gf
from gslam_jax.rbpf import tempering
from gslam_jax.tiled import numerics as nm


def _cess64(log_w: np.ndarray, log_lam: np.ndarray, phi: np.ndarray,
            chunk: int = 5000) -> np.ndarray:
    """Conditional ESS fraction in float64 for each exponent in ``phi`` (plain sums), for
    ``chunk`` exponents at a time."""
    w = np.exp(log_w - log_w.max())
    w = w / w.sum()
    out = []
    for p in np.array_split(phi, max(1, len(phi) // chunk)):
        x = p[:, None] * log_lam[None, :]
        x = x - x.max(axis=1, keepdims=True)
        out.append(np.sum(w * np.exp(x), axis=1) ** 2 / np.sum(w * np.exp(2 * x), axis=1))
    return np.concatenate(out)


_exponent = jax.jit(tempering.adaptive_exponent)


def _cases():
    rng = np.random.default_rng(0)
    J = 200
    uniform = np.full(J, -np.log(J))
    skewed = rng.normal(0, 1.5, J)
    skewed = skewed - np.log(np.sum(np.exp(skewed)))
    return [
        ("uniform, peaked", uniform, rng.normal(0, 40.0, J), 0.5),
        ("uniform, one outlier", uniform, np.r_[300.0, rng.normal(0, 1.0, J - 1)], 0.3),
        ("skewed, peaked", skewed, rng.normal(0, 25.0, J), 0.5),
        ("skewed, mild", skewed, rng.normal(0, 3.0, J), 0.1),
        ("benign: phi = 1", uniform, rng.normal(0, 0.05, J), 0.5),
    ]


@pytest.mark.parametrize("name,log_w,log_lam,target", _cases(), ids=[c[0] for c in _cases()])
def test_exponent_matches_a_grid_search_of_the_ess(name, log_w, log_lam, target):
    grid = np.linspace(0.0, 1.0, 100_001)
    cess = _cess64(log_w, log_lam, grid)
    assert np.all(np.diff(cess) <= 1e-12)  # non-increasing: bisection is valid
    brute = grid[np.flatnonzero(cess >= target)].max()
    phi = float(_exponent(jnp.asarray(log_w, jnp.float32),
                                            jnp.asarray(log_lam, jnp.float32), target))
    ref = nm.tempering_exponent(log_w, log_lam, target)
    assert phi <= 1.0
    step = grid[1]  # the brute force is exact to one grid step below
    assert brute - 1e-6 <= phi <= brute + step + 1e-6, (phi, brute)
    assert brute <= ref <= brute + step, (ref, brute)
    assert abs(phi - ref) <= 1e-5 * ref + 1e-7, (phi, ref)
    if brute < 1.0:  # the exponent holds the conditional ESS at the target
        assert _cess64(log_w, log_lam, np.array([ref]))[0] == pytest.approx(target, rel=1e-6)
    else:
        assert phi == 1.0 and ref == 1.0


def test_conditional_ess_is_the_ess_after_reweighting_from_uniform_weights():
    rng = np.random.default_rng(1)
    J = 50
    lam = rng.normal(0, 5, J)
    lw = jnp.full((J,), -np.log(J), jnp.float32)
    new = lw + 0.3 * lam
    ess = 1.0 / jnp.sum(jnp.exp(2 * (new - jax.nn.logsumexp(new))))
    assert float(tempering.conditional_ess(lw, jnp.asarray(lam, jnp.float32), 0.3)) == \
        pytest.approx(float(ess) / J, rel=1e-5)


def test_exponent_ignores_dead_particles_and_has_zero_gradient():
    lw = jnp.log(jnp.array([0.5, 0.5, 0.0, 0.0], jnp.float32))
    lam = jnp.array([0.0, 1.0, 1e4, -1e4], jnp.float32)
    phi = tempering.adaptive_exponent(lw, lam, 0.9)
    expect = nm.tempering_exponent(np.asarray(lw, np.float64), np.asarray(lam), 0.9)
    assert float(phi) == pytest.approx(expect, abs=1e-6) and 0.0 < expect < 1.0
    g = jax.grad(lambda s: tempering.adaptive_exponent(lw, s * lam, 0.9))(1.0)
    assert float(g) == 0.0


def _update(mode: str, target: float = 0.5):
    """One update of 64 particles spread over a map that holds one local map already."""
    L, J = 16, 64
    rng = np.random.default_rng(2)
    k = np.full((L, L), 5.0, np.float32)
    S = (rng.gamma(2.0, 0.05, (L, L)) * k).astype(np.float32)
    obs = jnp.asarray(np.stack([k, S], -1))
    cfg = gf.FilterConfig(J, (64, 64), (-5.12, -5.12), 0.16, L, unknown_cells="ignore",
                          tempering=mode, ess_target=target).validate()
    state = gf.init(cfg)
    u = gf.update_noise(jax.random.key(0), cfg).unknown_u
    update = jax.jit(gf.update, static_argnames="cfg")
    state, _ = update(state, obs, u, gf.FilterParams(), cfg)  # first map: no weights yet
    pose = jnp.asarray(rng.normal(0, [0.3, 0.3, 0.1], (J, 3)), jnp.float32)
    state = state._replace(pose=pose)
    return update(state, obs, u, gf.FilterParams(), cfg)[1]


def test_filter_update_tempers_to_the_target_and_fixed_mode_is_the_paper():
    fixed = _update("fixed")
    adaptive = _update("adaptive", 0.5)
    J = 64
    assert float(fixed.exponent) == 1.0
    assert float(fixed.ess) < 0.1 * J  # the paper's beta collapses this particle set
    assert 0.0 < float(adaptive.exponent) < 1.0
    assert float(adaptive.ess) == pytest.approx(0.5 * J, rel=1e-3)  # uniform weights before


def test_bad_tempering_settings_are_named():
    from gslam_jax.config import ConfigError, Config, apply_overrides

    with pytest.raises(ConfigError, match=r"\[filter\] tempering"):
        apply_overrides(Config(), ["filter.tempering=sometimes"])
    with pytest.raises(ConfigError, match=r"\[filter\] ess_target"):
        apply_overrides(Config(), ["filter.ess_target=-0.1"])
    with pytest.raises(ConfigError, match=r"\[filter\] ess_target"):
        apply_overrides(Config(), ["filter.ess_target=1.5"])
    with pytest.raises(ValueError, match="tempering"):
        gf.FilterConfig(4, (64, 64), (0.0, 0.0), 0.16, 16, tempering="auto").validate()
    with pytest.raises(ConfigError, match=r"\[filter\] proposal_exponent"):
        apply_overrides(Config(), ["filter.proposal_exponent=cloud"])
    with pytest.raises(ValueError, match="proposal_exponent 'cloud'"):
        gf.FilterConfig(4, (64, 64), (0.0, 0.0), 0.16, 16, proposal_exponent="cloud").validate()


def _normaliser_cess64(log_w, log_lam, log_prior, phi, chunk=500):
    """Conditional ESS fraction of the grid normalisers log Z_j(phi) in float64 (NumPy), for
    ``chunk`` exponents of ``phi`` at a time."""
    def logsumexp(a, axis):
        top = np.max(a, axis=axis, keepdims=True)
        return np.squeeze(top, axis) + np.log(np.sum(np.exp(a - top), axis=axis))

    w = np.exp(log_w - logsumexp(log_w, 0))
    out = []
    for p in np.array_split(phi, max(1, len(phi) // chunk)):
        inc = (logsumexp(p[:, None, None] * log_lam + log_prior, 2)
               - logsumexp(log_prior, 1))  # [P, J]
        x = inc - inc.max(axis=1, keepdims=True)
        out.append(np.sum(w * np.exp(x), axis=1) ** 2 / np.sum(w * np.exp(2 * x), axis=1))
    return np.concatenate(out)


_normaliser_exponent = jax.jit(tempering.normaliser_exponent)  # the target traced: one compile


@pytest.mark.parametrize("spread,target", [(30.0, 0.5), (5.0, 0.99), (0.01, 0.5)],
                         ids=["peaked", "stereo target", "benign: phi = 1"])
def test_normaliser_exponent_matches_a_grid_search(spread, target):
    """The informed proposal's exponent: the largest phi whose per-particle normalisers keep
    the conditional ESS at the target, against a float64 grid search in NumPy."""
    rng = np.random.default_rng(5)
    J, K = 64, 27
    g = rng.normal(size=(K, 3))
    log_prior = np.broadcast_to(-0.5 * np.sum(g * g, axis=1), (J, K))
    # each particle's score: a common shape around its own offset, plus its own level
    log_lam = (spread * rng.normal(size=(J, 1)) - spread * np.sum((g[None] - rng.normal(
        0, 0.5, (J, 1, 3))) ** 2, axis=2))
    log_w = rng.normal(0, 0.5, J)
    log_w = log_w - np.logaddexp.reduce(log_w)
    grid = np.linspace(0.0, 1.0, 20_001)
    cess = _normaliser_cess64(log_w, log_lam, log_prior, grid)
    assert np.all(np.diff(cess) <= 1e-9)  # non-increasing here: bisection is valid
    brute = grid[np.flatnonzero(cess >= target)].max()
    phi = float(_normaliser_exponent(
        jnp.asarray(log_w, jnp.float32), jnp.asarray(log_lam, jnp.float32),
        jnp.asarray(log_prior, jnp.float32), target))
    if brute == 1.0:
        assert phi == 1.0
    else:
        assert brute - 2e-4 <= phi <= brute + grid[1] + 2e-4, (phi, brute)
    # the spread the proposal leaves is smaller than the score's over the prior: a larger phi
    cloud = (log_w[:, None] + log_prior - np.logaddexp.reduce(log_prior, axis=1)[:, None])
    prior_phi = float(_exponent(jnp.asarray(cloud.ravel(), jnp.float32),
                                jnp.asarray(log_lam.ravel(), jnp.float32), target))
    assert phi >= prior_phi


def test_normaliser_exponent_ignores_dead_particles():
    log_lam = np.array([[0.0, -1.0], [-2.0, -3.0], [1e4, -1e4]], np.float32)
    log_prior = np.zeros((3, 2), np.float32)
    live = np.array([np.log(0.5), np.log(0.5), -np.inf], np.float32)
    phi = _normaliser_exponent(jnp.asarray(live), jnp.asarray(log_lam),
                               jnp.asarray(log_prior), 0.9)
    alone = _normaliser_exponent(jnp.asarray(live[:2] + 0.0), jnp.asarray(log_lam[:2]),
                                 jnp.asarray(log_prior[:2]), 0.9)
    assert float(phi) == float(alone) and 0.0 < float(phi) < 1.0
