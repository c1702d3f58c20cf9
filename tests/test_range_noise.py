"""[filter] range_noise: the measurement variance per range, estimated from a run's local maps
(``observations.range_noise_profile``) and added to what each weighed map cell predicts
(``rbpf.importance``), checked against an independent float64 eq. 26 (SciPy)."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.special import gammaln
from synthetic import make_run

from gslam_jax.config import Config, ConfigError, apply_overrides
from gslam_jax.driver import sizing
from gslam_jax.driver.observations import RING_M, range_noise_profile
from gslam_jax.rbpf import FilterParams
from gslam_jax.rbpf.importance import cell_noise, known_cell_terms, log_importance


def eq26(k, S, kp, Sp):
    """Eq. 26 in float64 from its textbook form (SciPy's gammaln): log density of v = S / k."""
    k2, S2 = k + kp, S + Sp
    return (gammaln(k2 / 2) - gammaln(k / 2) - gammaln(kp / 2)
            + 0.5 * (k * np.log(S) + kp * np.log(Sp) - k2 * np.log(S2)) - np.log(S / k))


def _cells(seed: int, M: int = 64):
    rng = np.random.default_rng(seed)
    k = rng.integers(1, 12, M).astype(np.float64)
    S = k * rng.uniform(1e-5, 1e-2, M)
    kp = np.where(rng.random(M) < 0.6, rng.integers(1, 80, M), 0).astype(np.float64)
    Sp = kp * rng.uniform(1e-5, 1e-2, M)
    noise = rng.uniform(0, 3e-3, M)
    return k, S, kp, Sp, noise


@pytest.mark.parametrize("seed", [0, 1])
def test_ignore_mode_adds_noise_to_the_predicted_variance(seed):
    k, S, kp, Sp, noise = _cells(seed)
    params = FilterParams(beta_prev=0.2, beta_new=0.2)
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    got = log_importance(f32(k), f32(S), f32(kp), f32(Sp), f32(k), f32(S),
                         jnp.bool_(False), params, "ignore", noise=f32(noise))
    prev = kp > 0
    want = eq26(k[prev], S[prev], kp[prev], Sp[prev] + kp[prev] * noise[prev]).mean() / 0.2
    np.testing.assert_allclose(float(got), want, rtol=2e-4, atol=2e-3)
    # no noise: the paper's eq. 30, and a zero profile gives exactly that
    none = log_importance(f32(k), f32(S), f32(kp), f32(Sp), f32(k), f32(S), jnp.bool_(False),
                          params, "ignore")
    zero = log_importance(f32(k), f32(S), f32(kp), f32(Sp), f32(k), f32(S), jnp.bool_(False),
                          params, "ignore", noise=jnp.zeros(len(k), jnp.float32))
    assert float(none) == float(zero)
    np.testing.assert_allclose(float(none), eq26(k[prev], S[prev], kp[prev], Sp[prev]).mean()
                               / 0.2, rtol=2e-4, atol=2e-3)


def test_known_cell_terms_are_eq26_at_the_known_cells_of_batched_footprints():
    (k, S, kp, Sp, noise), (k1, S1, kp1, Sp1, _) = _cells(2), _cells(3)
    k, S, kp, Sp = (np.stack(x) for x in ((k, k1), (S, S1), (kp, kp1), (Sp, Sp1)))
    k[0, 0], S[0, 0], kp[0, 0], Sp[0, 0] = 0, 0, 5, 0.01  # unobserved, its map cell known
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    known, lam = known_cell_terms(f32(k), f32(S), f32(kp), f32(Sp), f32(noise))
    want_known = (k > 0) & (kp > 0)
    np.testing.assert_array_equal(np.asarray(known), want_known)
    assert want_known.any() and (~want_known).any() and not want_known[0, 0]
    Sp_noisy = Sp + kp * noise[None, :]  # the same noise per observed cell for every row
    np.testing.assert_allclose(np.asarray(lam)[want_known],
                               eq26(k, S, kp, Sp_noisy)[want_known], rtol=2e-4, atol=2e-3)
    assert np.all(np.asarray(lam)[~want_known] == 0)


@pytest.mark.parametrize("draws", [64, 16])  # borrowed cell per observed cell / cell c mod D
def test_sample_mode_adds_noise_to_borrowed_cells_too(draws):
    k, S, kp, Sp, noise = _cells(2)
    rng = np.random.default_rng(3)
    kb = rng.integers(1, 60, draws).astype(np.float64)
    Sb = kb * rng.uniform(1e-5, 1e-2, draws)
    params = FilterParams(beta_prev=0.3, beta_new=0.7)
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    got = log_importance(f32(k), f32(S), f32(kp), f32(Sp), f32(kb), f32(Sb), jnp.bool_(True),
                         params, "sample", noise=f32(noise))
    prev = kp > 0
    c = np.arange(len(k)) % draws
    lam_prev = eq26(k[prev], S[prev], kp[prev], Sp[prev] + kp[prev] * noise[prev])
    lam_new = eq26(k[~prev], S[~prev], kb[c][~prev], Sb[c][~prev] + kb[c][~prev] * noise[~prev])
    want = (lam_prev.sum() / 0.3 + lam_new.sum() / 0.7) / len(k)
    np.testing.assert_allclose(float(got), want, rtol=2e-4, atol=2e-3)


def test_cell_noise_follows_the_observed_cells():
    profile = jnp.arange(16, dtype=jnp.float32) * 1e-4
    index = jnp.array([3, 0, 15, 7], jnp.int32)
    np.testing.assert_allclose(cell_noise(index, FilterParams(range_noise=profile)),
                               [3e-4, 0.0, 1.5e-3, 7e-4], rtol=1e-6)
    assert cell_noise(index, FilterParams()) is None


def _synthetic_obs(a: float, b: float, L: int = 64, res: float = 0.16, maps: int = 8,
                   seed: int = 0) -> np.ndarray:
    """Local maps whose cells' observed variance is a + b r^2 (r: the cell's range) times a
    random terrain factor in [0.5, 1.5], k = 5; a few cells unobserved."""
    rng = np.random.default_rng(seed)
    c = (np.arange(L) - L // 2 + 0.5) * res
    r2 = c[:, None] ** 2 + c[None, :] ** 2
    v = (a + b * r2)[None] * rng.uniform(0.5, 1.5, (maps, L, L))
    k = np.where(rng.random((maps, L, L)) < 0.9, 5.0, 0.0)
    return np.stack([k, k * v], axis=-1)


def test_profile_recovers_a_variance_growing_with_range():
    res, a, b = 0.16, 1e-4, 2e-5
    obs = _synthetic_obs(a, b, res=res)
    got = range_noise_profile(obs, res)
    L = obs.shape[1]
    c = (np.arange(L) - L // 2 + 0.5) * res
    r = np.hypot(c[:, None], c[None, :]).reshape(-1)
    assert got.shape == (L * L,) and got.dtype == np.float32
    assert np.all(got >= 0)
    assert np.all(got[r < RING_M] == 0.0)  # the nearest ring is the zero
    # each ring's median is that of a + b r^2 over the ring (the terrain factor has median 1),
    # less the nearest ring's: check mid-range rings to 10 %
    for ring in (4, 6, 8):
        sel = (r // RING_M) == ring
        want = b * np.median(r[sel] ** 2) - b * np.median(r[r < RING_M] ** 2)
        np.testing.assert_allclose(np.median(got[sel]), want, rtol=0.1)
    # non-decreasing with range
    order = np.argsort(r)
    assert np.all(np.diff(got[order]) >= 0)


def test_profile_of_nothing_observed_is_zero():
    obs = np.zeros((3, 16, 16, 2))
    assert not range_noise_profile(obs, 0.16).any()


def test_filter_params_estimates_the_profile_only_when_asked():
    run, _ = make_run(seed=0, steps=40)
    config = Config()
    assert sizing.filter_params(config, run).range_noise is None
    prof = apply_overrides(config, ["filter.range_noise=profile"])
    noise = sizing.filter_params(prof, run).range_noise
    assert noise.shape == (run.local_maps.shape[1] ** 2,)
    # a short run: every local map is used, as the filter converts them
    from gslam_jax.driver.observations import local_observations
    whole = range_noise_profile(local_observations(run, config.map.min_variance), run.resolution)
    np.testing.assert_allclose(np.asarray(noise), whole, rtol=1e-5, atol=1e-12)
    with pytest.raises(ConfigError, match="range_noise"):
        sizing.filter_params(prof)  # no run: named, not silently dropped


def test_config_rejects_an_unknown_range_noise():
    with pytest.raises(ConfigError, match="range_noise"):
        apply_overrides(Config(), ["filter.range_noise=guess"])
    cfg = dataclasses.replace(Config().filter, range_noise="profile")
    assert cfg.range_noise == "profile"


def test_compare_refuses_a_noise_the_tiled_reference_lacks():
    from gslam_jax.app.compare import _compare

    config = apply_overrides(Config(), ["filter.range_noise=profile"])
    with pytest.raises(ConfigError, match="tiled reference"):
        _compare(None, config, print, particles=2, unknown_cells=None, tile_size=None, seed=0,
                 store=None, pool_tiles=None)


def test_running_profile_keeps_evenly_spaced_maps_and_is_causal(monkeypatch):
    """``RunningRangeNoise`` with room for 4 maps, fed 12 distinct ones: it keeps maps 0, 4, 8
    (every map, then every other, then every fourth) and estimates again at 1, 2, 4, 8 and 12
    maps, each time the profile of exactly the maps kept so far (computed here directly)."""
    import gslam_jax.driver.observations as observations
    from gslam_jax.rbpf import cells

    monkeypatch.setattr(observations, "PROFILE_MAPS", 4)
    monkeypatch.setattr(observations, "RING_MIN_CELLS", 20)
    config, L, res = Config(), 32, 0.16
    centres = (np.arange(L) - L // 2 + 0.5) * res
    r2 = centres[:, None] ** 2 + centres[None, :] ** 2
    rng = np.random.default_rng(4)
    maps = []
    for m in range(12):  # variance a + b_m r^2, with a slope of its own per map
        var = 1e-4 + (m + 1) * 1e-5 * r2
        n = rng.integers(3, 9, (L, L)).astype(np.float64)
        z = rng.normal(0, 1, (L, L, 9)) * np.sqrt(var)[..., None]
        z = np.where(np.arange(9) < n[..., None], z, 0.0)
        maps.append(np.stack([n, z.sum(-1), (z ** 2).sum(-1)], -1))

    def direct(picked):
        obs = cells.obs_from_stats(np.stack([maps[i] for i in picked]), config.map.min_variance,
                                   config.map.obs_weight, config.map.min_points)
        return range_noise_profile(obs, res)

    running = observations.RunningRangeNoise(config, L, res)
    assert not running.profile.any() and running.profile.shape == (L * L,)
    estimated_at, expect = [], {1: [0], 2: [0, 1], 4: [0, 1, 2, 3], 8: [0, 2, 4, 6],
                                12: [0, 4, 8]}
    for m in range(12):
        if running.add(maps[m]):
            estimated_at.append(m + 1)
            np.testing.assert_array_equal(running.profile, direct(expect[m + 1]))
    assert estimated_at == [1, 2, 4, 8, 12]
    assert running.profile.any() and running.seen == 12
