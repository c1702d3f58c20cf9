"""The observation-informed proposal (rbpf/proposal.py): its Gaussian fit, its importance
weights against brute-force integration, its covariance against Monte Carlo of the motion model,
and the filter with it."""

from __future__ import annotations

import functools
import math
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from gslam_jax.rbpf import kernel, proposal
from gslam_jax.rbpf.motion import MotionParams, apply_motion


def _quadratic_score(g: np.ndarray, centre: np.ndarray, precision: np.ndarray) -> np.ndarray:
    """A synthetic log score in whitened coordinates: -(g - c)^T A (g - c) / 2."""
    d = g - centre
    return -0.5 * np.einsum("...a,ab,...b->...", d, precision, d)


@partial(jax.jit, static_argnames=("points", "stages"))
def _fit_jitted(c: jax.Array, A: jax.Array, phi: jax.Array, points: int, stages: int):
    def score(g):  # traced: the stages are one lax.scan
        d = g - c
        return -0.5 * jnp.einsum("...a,ab,...b->...", d, A, d)

    return proposal.fit_proposal(score, 1, points, 2.0, stages, lambda log_lam, log_prior: phi)


def _fit(centre: np.ndarray, precision: np.ndarray, phi: float, points: int = 3,
         stages: int = 2):
    """The staged fit of one particle whose score is ``_quadratic_score`` (one compilation
    for every centre, precision and exponent)."""
    mu, q_chol, got = _fit_jitted(jnp.asarray(centre, jnp.float32),
                                  jnp.asarray(precision, jnp.float32), jnp.float32(phi),
                                  points, stages)
    assert float(got) == pytest.approx(phi)
    return mu, q_chol


@jax.jit
def _proposal_draws_and_correction(mu: jax.Array, q_chol: jax.Array):
    """200,000 draws g from N(mu, Q) and their log N(g; 0, I) - log N(g; mu, Q)."""
    z = jax.random.normal(jax.random.key(0), (200_000, 3))
    g = mu + z @ q_chol[0].T
    eye = jnp.broadcast_to(jnp.eye(3), (g.shape[0], 3, 3))
    correction = (proposal._log_normal(g, jnp.zeros_like(g), eye)
                  - proposal._log_normal(g, jnp.broadcast_to(mu, g.shape),
                                         jnp.broadcast_to(q_chol, eye.shape)))
    return g, correction


@functools.lru_cache(maxsize=1)
def _integration_grid() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The brute-force integration's fine grid: its axis, its 141^3 points [N, 3] and N(g; 0, I)
    at each (built once, shared by both precisions; read-only)."""
    axis = np.linspace(-7, 7, 141)
    G = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    prior_pdf = stats.multivariate_normal(np.zeros(3), np.eye(3)).pdf(G)
    for a in (axis, G, prior_pdf):
        a.flags.writeable = False
    return axis, G, prior_pdf


@pytest.mark.slow
@pytest.mark.parametrize("precision", [np.diag([4.0, 9.0, 25.0]), np.diag([0.0, 9.0, 25.0])])
def test_weights_are_exact_importance_weights_of_the_tempered_target(precision):
    """E_q[exp(correction + phi log lambda)] is the target's normaliser
    Z = int N(g; 0, I) lambda(g)^phi dg, whatever Gaussian the fit chose; Z by brute-force
    integration on a fine grid (and in closed form), the expectation by Monte Carlo."""
    centre = np.array([0.8, -0.5, 0.3])
    phi = 0.7
    mu, q_chol = _fit(centre, precision, phi)
    g, correction = _proposal_draws_and_correction(mu, q_chol)
    w = np.exp(np.asarray(correction, np.float64)
               + phi * _quadratic_score(np.asarray(g, np.float64), centre, precision))
    axis, G, prior_pdf = _integration_grid()
    integrand = prior_pdf * np.exp(phi * _quadratic_score(G, centre, precision))
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


@jax.jit
def _propagated_and_sampled(controls: jax.Array, params: MotionParams):
    """The proposal's mean and accumulated covariance over ``controls`` from the origin, and
    100,000 samples of the motion model over the same controls (frame t's normals from key t)."""
    def frame(carry, xs):
        pose, cov, samples = carry
        t, u = xs
        pose, cov = proposal.propagate_mean(pose, cov, u, params)
        eps = jax.random.normal(jax.random.key(t), samples.shape)
        return (pose, cov, apply_motion(samples, u, eps, params)), None

    start = (jnp.zeros(3), jnp.zeros((3, 3)), jnp.zeros((100_000, 3)))
    (pose, cov, samples), _ = jax.lax.scan(frame, start,
                                           (jnp.arange(controls.shape[0]), controls))
    return pose, cov, samples


@pytest.mark.parametrize("alpha_cross", [0.0, 0.03])
def test_accumulated_covariance_matches_monte_carlo_of_the_motion_model(alpha_cross):
    params = MotionParams(0.05, 0.01, 0.05, alpha_cross)
    controls = jnp.asarray(np.tile([0.3, 0.0, 0.02], (20, 1)), jnp.float32)
    pose, cov, samples = _propagated_and_sampled(controls, params)
    emp = np.cov(np.asarray(samples, np.float64).T)
    np.testing.assert_allclose(np.asarray(samples).mean(0), np.asarray(pose), atol=3e-3)
    np.testing.assert_allclose(np.asarray(cov), emp, rtol=0.08, atol=2e-5)


# ------------------------------------------------------------------ the filter with it

# The filter's functions as the tests call them, each compiled once per configuration rather
# than dispatched op by op.
_update = jax.jit(kernel.update, static_argnames=("cfg",))
_score_candidates = jax.jit(proposal.score_candidates, static_argnames=("cfg",))


def _small_case(points: int = 3, J: int = 4, seed: int = 0):
    """A 64 x 64 map with known and unknown cells, a 16 x 16 local map, J particles around
    the map's centre with an accumulated prior covariance."""
    from gslam_jax.rbpf import densestore
    from gslam_jax.rbpf.types import FilterConfig, FilterState

    rng = np.random.default_rng(seed)
    cfg = FilterConfig(num_particles=J, map_shape=(64, 64), map_origin=(0.0, 0.0),
                       resolution=0.16, local_size=16, proposal="informed",
                       proposal_points=points, tempering="fixed", unknown_cells="ignore")
    known = rng.uniform(size=(64, 64)) < 0.8
    k = np.where(known, rng.integers(1, 30, (64, 64)), 0).astype(np.float32)
    S = np.where(known, k * rng.uniform(0.001, 0.05, (64, 64)), 0).astype(np.float32)
    dense = densestore.DenseMaps(jnp.broadcast_to(k, (J, 64, 64)), jnp.broadcast_to(S, (J, 64, 64)),
                                 jnp.zeros((J, 0, 0, 2), jnp.uint32),
                                 jnp.zeros((J, 0, 0), jnp.int32), jnp.array([0, 64], jnp.int32))
    pose = jnp.asarray(np.column_stack([5.1 + 0.05 * rng.normal(size=J),
                                        5.0 + 0.05 * rng.normal(size=J),
                                        0.3 + 0.02 * rng.normal(size=J)]), jnp.float32)
    cov = jnp.broadcast_to(jnp.diag(jnp.asarray([0.01, 0.004, 0.002], jnp.float32)), (J, 3, 3))
    state = FilterState(pose, jnp.full((J,), -math.log(J), jnp.float32), dense, jnp.int32(0),
                        cov)
    lk = np.where(rng.uniform(size=(16, 16)) < 0.6, rng.integers(1, 12, (16, 16)), 0)
    local = np.stack([lk, lk * rng.uniform(0.001, 0.05, (16, 16))], -1).astype(np.float32)
    return cfg, state, jnp.asarray(local), (k, S)


def _brute_log_lambda(pose, local, k_map, S_map, cfg, beta, stride=1):
    """Eq. 26 with eq. 30 in float64 with SciPy, one observed cell at a time; with ``stride``
    only every stride-th observed cell in row-major order."""
    from scipy.special import gammaln

    L = cfg.local_size
    total, n, seen = 0.0, 0, -1
    for a in range(L):
        for b in range(L):
            ko, So = float(local[a, b, 0]), float(local[a, b, 1])
            if ko <= 0:
                continue
            seen += 1
            if seen % stride:
                continue
            ca, cb = a - L // 2 + 0.5, b - L // 2 + 0.5
            c, s = math.cos(pose[2]), math.sin(pose[2])
            i = math.floor(pose[0] / cfg.resolution + c * ca - s * cb)
            j = math.floor(pose[1] / cfg.resolution + s * ca + c * cb)
            kp, Sp = float(k_map[i, j]), float(S_map[i, j])
            if kp <= 0:
                continue
            k2, S2 = ko + kp, So + Sp
            total += (gammaln(k2 / 2) - gammaln(ko / 2) - gammaln(kp / 2)
                      + 0.5 * (ko * math.log(So) + kp * math.log(Sp) - k2 * math.log(S2))
                      - math.log(So / ko))
            n += 1
    return total / (beta * n) if n else 0.0


@pytest.mark.slow
@pytest.mark.parametrize("stride", [1, 3])
def test_candidate_scores_match_brute_force_eq_26(stride):
    """With ``proposal_cell_stride`` s the candidates are scored on every s-th observed cell."""
    from gslam_jax.rbpf.footprint import compact_observation
    from gslam_jax.rbpf.types import FilterParams

    cfg, state, local, (k, S) = _small_case()
    cfg = cfg._replace(proposal_cell_stride=stride)
    params = FilterParams()
    obs = compact_observation(local, cfg)
    chol = proposal.prior_factor(state.prior_cov)
    grid, _ = proposal.candidate_grid(3, 2.0)
    g = jnp.broadcast_to(grid, (cfg.num_particles,) + grid.shape)
    got = np.asarray(_score_candidates(state.maps, state.pose, chol, g,
                                       jnp.zeros((cfg.num_particles, 0)), obs, params, cfg))
    poses = np.asarray(state.pose)[:, None, :] + np.einsum("jab,kb->jka", np.asarray(chol),
                                                           np.asarray(grid))
    for j, kk in [(0, 0), (1, 5), (2, 13), (3, 26)]:
        want = _brute_log_lambda(poses[j, kk].astype(np.float64), np.asarray(local), k, S, cfg,
                                 float(params.beta_prev), stride)
        assert got[j, kk] == pytest.approx(want, rel=2e-4, abs=1e-2)
    if stride > 1:  # a real subset: not the full score
        full = _brute_log_lambda(poses[0, 0].astype(np.float64), np.asarray(local), k, S, cfg,
                                 float(params.beta_prev))
        assert got[0, 0] != pytest.approx(full, rel=1e-3)


@pytest.mark.slow
def test_one_candidate_reduces_to_the_motion_proposals_update():
    """proposal_points = 1: the pose is a draw of the prior, and the update is exactly the
    motion proposal's update at that pose (no correction, the same weights and maps)."""
    cfg, state, local, _ = _small_case(points=1)
    z = jax.random.normal(jax.random.key(3), (cfg.num_particles, 3))
    params = kernel.FilterParams()
    informed, info_i = _update(state, local, jnp.zeros((cfg.num_particles, 0)), params,
                                     cfg, z)
    drawn = state.pose + jnp.einsum("jab,jb->ja", proposal.prior_factor(state.prior_cov), z)
    motion_cfg = cfg._replace(proposal="motion")
    moved = state._replace(pose=drawn, prior_cov=None)
    plain, info_m = _update(moved, local, jnp.zeros((cfg.num_particles, 0)), params,
                                  motion_cfg)
    np.testing.assert_array_equal(informed.pose, drawn)
    np.testing.assert_array_equal(informed.log_w, plain.log_w)
    np.testing.assert_array_equal(informed.maps.k, plain.maps.k)
    np.testing.assert_array_equal(np.asarray(informed.prior_cov), 0.0)
    assert float(info_i.log_lik) == float(info_m.log_lik)


@partial(jax.jit, static_argnames=("cfg",))
def _draw(maps_, pose, prior_cov, z, unknown_u, obs, params, cfg):
    """proposal.draw at a fixed exponent of 1, compiled once per configuration."""
    return proposal.draw(maps_, pose, prior_cov, z, lambda lam, p: jnp.float32(1.0), unknown_u,
                         obs, params, cfg)


@pytest.mark.parametrize("stride", [1, 3])
def test_informed_weights_are_the_tempered_score_plus_the_correction(stride):
    """The update's weights with the informed proposal: phi log lambda at the drawn pose (eq.
    26, brute force, every observed cell even when the fit scored every third) plus the
    proposal's correction, normalised."""
    from gslam_jax.rbpf.footprint import compact_observation

    cfg, state, local, (k, S) = _small_case(points=3)
    cfg = cfg._replace(proposal_cell_stride=stride)
    z = jax.random.normal(jax.random.key(4), (cfg.num_particles, 3))
    params = kernel.FilterParams()
    new, info = _update(state, local, jnp.zeros((cfg.num_particles, 0)), params, cfg, z)
    d = _draw(state.maps, state.pose, state.prior_cov, z, jnp.zeros((cfg.num_particles, 0)),
              compact_observation(local, cfg), params, cfg)
    np.testing.assert_allclose(new.pose, d.pose, atol=1e-6)
    lam = np.array([_brute_log_lambda(np.asarray(p, np.float64), np.asarray(local), k, S, cfg,
                                      float(params.beta_prev)) for p in np.asarray(d.pose)])
    unnorm = np.asarray(state.log_w, np.float64) + lam + np.asarray(d.log_correction)
    want = unnorm - np.logaddexp.reduce(unnorm)
    np.testing.assert_allclose(new.log_w, want, atol=2e-3)
    assert float(info.exponent) == 1.0  # fixed tempering: the paper's beta alone


@jax.jit  # one compilation for the rules' functions, not one per operation
def _exponents(log_w, lam, prior, cloud):
    from gslam_jax.rbpf import tempering

    return (tempering.normaliser_exponent(log_w, lam, prior, 0.9),
            tempering.adaptive_exponent(cloud, lam.ravel(), 0.9))


@functools.lru_cache(maxsize=1)
def _first_grid_exponents() -> tuple[float, float]:
    """Both rules' exponents on the first grid's brute-force scores (eq. 26) of the J = 6
    small case: (normaliser, prior); computed once, for the test of either rule."""
    cfg, state, local, (k, S) = _small_case(points=3, J=6)
    params = kernel.FilterParams()
    grid, _ = proposal.candidate_grid(3, 2.0)
    chol = np.asarray(proposal.prior_factor(state.prior_cov))
    poses = np.asarray(state.pose)[:, None, :] + np.einsum("jab,kb->jka", chol, np.asarray(grid))
    lam = np.array([[_brute_log_lambda(p.astype(np.float64), np.asarray(local), k, S, cfg,
                                       float(params.beta_prev)) for p in row] for row in poses])
    log_prior = np.broadcast_to(-0.5 * np.sum(np.asarray(grid) ** 2, axis=1), lam.shape)
    lam32, prior32 = jnp.asarray(lam, jnp.float32), jnp.asarray(log_prior, jnp.float32)
    cloud = np.asarray(state.log_w)[:, None] + log_prior
    cloud = cloud - np.logaddexp.reduce(cloud.ravel())
    by_normaliser, by_prior = map(float, _exponents(state.log_w, lam32, prior32,
                                                    jnp.asarray(cloud.ravel(), jnp.float32)))
    return by_normaliser, by_prior


@pytest.mark.slow
@pytest.mark.parametrize("rule", ["prior", "normaliser"])
def test_the_adaptive_exponent_is_chosen_from_the_first_grid(rule):
    """Adaptive tempering with the informed proposal: the update's exponent is the rule's on
    the first grid's brute-force scores (eq. 26): the candidate cloud's conditional ESS over
    the prior ("prior") or the per-particle normalisers' ("normaliser"), and the normaliser's
    exponent is the larger (it does not count the spread the proposal absorbs)."""
    cfg, state, local, _ = _small_case(points=3, J=6)
    cfg = cfg._replace(tempering="adaptive", ess_target=0.9, proposal_exponent=rule)
    z = jax.random.normal(jax.random.key(5), (cfg.num_particles, 3))
    params = kernel.FilterParams()
    _, info = _update(state, local, jnp.zeros((cfg.num_particles, 0)), params, cfg, z)
    by_normaliser, by_prior = _first_grid_exponents()
    assert 0.0 < by_prior < by_normaliser
    want = by_normaliser if rule == "normaliser" else by_prior
    assert float(info.exponent) == pytest.approx(want, rel=2e-3)


@partial(jax.jit, static_argnames=("cfg",))
def _scores_by_update_reads(store_, pose, chol, grid, u, obs, params, cfg):
    """Each candidate's log lambda (eq. 26) from the update's own footprint reads at its pose
    [J, K]."""
    from gslam_jax.rbpf import cells
    from gslam_jax.rbpf.footprint import read_footprints
    from gslam_jax.rbpf.importance import log_lambda

    rows = jnp.arange(cfg.num_particles, dtype=jnp.int32)
    log_v = cells.log_v_obs(obs.k, obs.S)
    return jax.lax.map(lambda t: log_lambda(read_footprints(
        store_, pose + jnp.einsum("jab,b->ja", chol, t), rows, u, obs, cfg),
        log_v, params, cfg), grid).T


@pytest.mark.slow
@pytest.mark.parametrize("store,prior_std,window_bytes", [
    ("shared", 0.1, None),  # every candidate inside its particle's window
    ("dense", 1.5, None),   # a prior wider than the window: read from the maps instead
    ("dense", 0.1, 0),      # windows over budget: every candidate read from the maps
], ids=["window", "wide-prior", "no-window"])
def test_windowed_candidate_scores_equal_the_updates_reads(store, prior_std, window_bytes,
                                                           monkeypatch):
    """score_candidates reads each particle's map once (a window and eq. 31's draws) for all
    its candidates; its scores are those of the update's own footprint reads
    (``read_footprints``) at each candidate pose, inside the window or not ("dense" with
    "ignore" inside it: ``test_candidate_scores_match_brute_force_eq_26``)."""
    from gslam_jax.rbpf import maps
    from gslam_jax.rbpf.footprint import compact_observation
    from gslam_jax.rbpf.types import FilterParams

    if window_bytes is not None:
        monkeypatch.setattr(proposal, "WINDOW_BYTES", window_bytes)
    cfg, state, local, (k, S) = _small_case(J=3)
    assert (proposal.candidate_window(cfg) == 0) == (window_bytes == 0)
    cfg = cfg._replace(store=store, tile=16, pool_tiles=64, unknown_cells="sample",
                       unknown_samples=32).validate()
    store_ = maps.init(cfg, (jnp.asarray(k), jnp.asarray(S)))
    J = cfg.num_particles
    var = jnp.asarray([prior_std ** 2, prior_std ** 2, 0.002], jnp.float32)
    chol = proposal.prior_factor(jnp.broadcast_to(jnp.diag(var), (J, 3, 3)))
    grid, _ = proposal.candidate_grid(3, 2.0)
    g = jnp.broadcast_to(grid, (J,) + grid.shape)
    u = jax.random.uniform(jax.random.key(5), (J, cfg.unknown_samples))
    obs = compact_observation(local, cfg)
    params = FilterParams()
    # a wrapper of its own: a trace cached by an earlier case with the same cfg would keep
    # that case's WINDOW_BYTES
    score_candidates = jax.jit(partial(proposal.score_candidates), static_argnames=("cfg",))
    got = np.asarray(score_candidates(store_, state.pose, chol, g, u, obs, params, cfg))

    want = np.asarray(_scores_by_update_reads(store_, state.pose, chol, grid, u, obs, params,
                                              cfg))
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)
    # the wide prior's outer candidates do leave the window (the fallback path is exercised)
    reach = prior_std * 2.0 / cfg.resolution
    assert (reach > cfg.reach // 2 + 1) == (prior_std > 1.0)



def test_the_windows_stay_within_their_memory_budget():
    """J = 2000 with KITTI's 128 x 128 local maps would need 1.2 GB of windows: none."""
    from gslam_jax.rbpf.types import FilterConfig

    def cfg(J, L):
        return FilterConfig(num_particles=J, map_shape=(640, 640), map_origin=(0.0, 0.0),
                            resolution=0.16, local_size=L)

    side = proposal.candidate_window(cfg(200, 128))
    assert side > 2 * cfg(200, 128).reach and 8 * 200 * side ** 2 <= proposal.WINDOW_BYTES
    assert proposal.candidate_window(cfg(2000, 128)) == 0


def test_a_start_spread_is_the_informed_proposals_first_prior():
    """With the informed proposal, rbpf.init keeps every particle at the start and makes the
    start spread its prior covariance; on a map with nothing to score (every cell unknown,
    eq. 30) the first update then draws the start from exactly that prior, N(start,
    diag(sigma^2)), and the weights stay equal."""
    from scipy import stats as st

    from gslam_jax import rbpf
    from gslam_jax.rbpf.types import FilterConfig

    J = 1000
    cfg = FilterConfig(num_particles=J, map_shape=(64, 64), map_origin=(0.0, 0.0),
                       resolution=0.16, local_size=16, unknown_cells="ignore",
                       proposal="informed", tempering="fixed", update_map=False)
    start = np.array([5.0, 5.1, 0.3], np.float32)
    sigma = np.array([0.2, 0.1, 0.05], np.float32)
    state = rbpf.init(cfg, start, key=jax.random.key(0), start_sigma=sigma)
    np.testing.assert_array_equal(state.pose, np.broadcast_to(start, (J, 3)))
    np.testing.assert_allclose(state.prior_cov, np.broadcast_to(np.diag(sigma ** 2), (J, 3, 3)))
    motion = rbpf.init(cfg._replace(proposal="motion"), start, key=jax.random.key(0),
                       start_sigma=sigma)
    assert np.all(np.std(np.asarray(motion.pose), axis=0) > 0.5 * sigma)  # drawn at once

    local = np.zeros((16, 16, 2), np.float32)
    local[4:12, 4:12] = (5.0, 0.05)
    z = jax.random.normal(jax.random.key(1), (J, 3))
    new, _ = _update(state, jnp.asarray(local), jnp.zeros((J, 0)), rbpf.FilterParams(),
                         cfg, z)
    drawn = (np.asarray(new.pose, np.float64) - start) / sigma
    for axis in range(3):  # standard normal per axis
        assert st.kstest(drawn[:, axis], "norm").pvalue > 1e-3, axis
    np.testing.assert_allclose(new.log_w, -math.log(J), atol=1e-5)
