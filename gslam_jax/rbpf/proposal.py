"""The observation-informed proposal: each particle's pose at an update drawn from a Gaussian
fitted to its map score times its motion prior (as GMapping's improved proposal, Grisetti,
Stachniss and Burgard 2007), weighted so that the filter stays a correct SMC.

Between updates the particles move by the motion model's mean (eqs. 1-3 with zero noise) and
carry the linearised covariance of the motion noise accumulated since their last update
(``propagate_mean``). At an update, particle j's prior over its pose is N(m_j, P_j). In the
whitened coordinates g (pose = m_j + C_j g, C_j C_j^T = P_j) the prior is N(0, I). The local map
is scored (eq. 26 with eq. 30 / 31, tempered by phi) at candidates g_k; the target at a
candidate is

    s_k = phi log lambda_j(m_j + C_j g_k) - |g_k|^2 / 2,

and the proposal is the Gaussian q_j = N(mu_j, Q_j) of the quadratic fitted to s at the
candidates (``fit_proposal``): a grid around the prior mean first, then the same grid in the
coordinates of that first fit, so that the last fit is made where the target's mass is. Where
the score is flat (a straight road's along-track direction) the weights follow the prior there,
so q_j follows the prior in that direction and is sharp only where the map is informative: no
global switch. A pose drawn from q_j gets the exact importance weight of the tempered target,

    log w_j += phi log lambda_j(x) + log N(g; 0, I) - log N(g; mu_j, Q_j),

whatever q_j is: the fit only decides how efficient the draw is, never what the filter targets.
With a single candidate (``proposal_points = 1``) q_j is the prior itself and the increment is
the motion proposal's, phi log lambda_j(x).

The tempering exponent phi is chosen once per update from the first grid's scores and used by
both the fit and the weights: 1 with fixed tempering; with adaptive tempering the rule of
``tempering`` applied either to the cloud of every particle's candidates weighted by their
prior density (``proposal_exponent = "prior"``: the spread the motion proposal's particles
would have, which the particles themselves, all at their prior means, do not show) or to each
particle's normaliser over its grid (``"normaliser"``: the spread the proposal leaves in the
weights, ``tempering.normaliser_exponent``). The candidates
are scored for all particles at once, one candidate after another (``lax.map``), by the update's
eq. 26 kernel on footprints gathered from one read of each particle's map around its prior mean
(``candidate_scorer``, once per update for every stage); with ``proposal_cell_stride`` s > 1 on
every s-th observed cell only (``thin_observation``: the fit sees fewer cells, the weight at the
drawn pose all of them).
"""

from __future__ import annotations

import math
from functools import partial
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array, lax

from gslam_jax.rbpf import cells, maps, tempering
from gslam_jax.rbpf.footprint import footprint_at, read_borrowed
from gslam_jax.rbpf.importance import cell_noise, log_lambda
from gslam_jax.rbpf.motion import MotionParams, apply_motion, motion_stds, world_step
from gslam_jax.rbpf.types import FilterConfig, FilterParams, FilterState, Observation

__all__ = ["Draw", "Score", "Exponent", "propagate_mean", "motion_covariance_step", "prior_factor",
           "candidate_grid", "candidate_window", "WINDOW_BYTES", "thin_observation",
           "score_candidates", "candidate_scorer", "update_exponent", "fit_proposal", "draw",
           "quadratic_design", "quadratic_hessian", "JITTER", "Proposal", "move_by_motion",
           "move_by_mean", "UpdateDraw", "ProposalRule", "RULES", "select"]

# Variance floor added to the accumulated prior (m^2, m^2, rad^2): one step of the motion model
# moves the position along-track only (with alpha_cross = 0), so the covariance is singular
# until the heading noise has spread it across; the floor keeps the Cholesky factor finite.
JITTER = (1e-8, 1e-8, 1e-10)


def motion_covariance_step(pose: Array, cov: Array, u: Array, params: MotionParams) -> Array:
    """Linearised covariance [..., 3, 3] of the pose after one motion step from ``pose`` with
    covariance ``cov`` and control ``u`` (eqs. 1-3: along-track scale noise alpha_d, heading
    noise sigma_theta, cross-track noise alpha_cross): F P F^T + G G^T."""
    _, _, sigma_theta = motion_stds(u, params)
    wx, wy = world_step(pose, u)
    zero, one = jnp.zeros_like(wx), jnp.ones_like(wx)
    F = jnp.stack([jnp.stack([one, zero, -wy], -1),
                   jnp.stack([zero, one, wx], -1),
                   jnp.stack([zero, zero, one], -1)], -2)
    a_c = params.alpha_cross
    G = jnp.stack([jnp.stack([params.alpha_d * wx, zero, -a_c * wy], -1),
                   jnp.stack([params.alpha_d * wy, zero, a_c * wx], -1),
                   jnp.stack([zero, sigma_theta * one, zero], -1)], -2)
    return F @ cov @ jnp.swapaxes(F, -1, -2) + G @ jnp.swapaxes(G, -1, -2)


def propagate_mean(pose: Array, cov: Array, u: Array, params: MotionParams
                   ) -> tuple[Array, Array]:
    """One frame of the informed proposal's prediction: the motion model's mean (eq. 1 without
    noise) and the accumulated covariance (``motion_covariance_step``)."""
    new = apply_motion(pose, u, jnp.zeros(pose.shape[:-1] + (3,), pose.dtype), params)
    return new, motion_covariance_step(pose, cov, u, params)


def candidate_grid(points: int, span: float) -> tuple[Array, float]:
    """The whitened candidate offsets [points^3, 3] on a regular grid over [-span, span] per
    axis (the centre, g = 0, first), and the grid spacing h (0 for a single point)."""
    if points == 1:
        return jnp.zeros((1, 3), jnp.float32), 0.0
    axis = jnp.linspace(-span, span, points, dtype=jnp.float32)
    g = jnp.stack(jnp.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    order = jnp.argsort(jnp.sum(g * g, axis=1), stable=True)  # the centre first
    return g[order], 2.0 * span / (points - 1)


def prior_factor(cov: Array) -> Array:
    """Lower Cholesky factor [J, 3, 3] of the prior covariance with the JITTER floor."""
    return jnp.linalg.cholesky(cov + jnp.diag(jnp.asarray(JITTER, cov.dtype)))


# Most bytes the windows of all particles may take (k and S, float32); above it (e.g. J = 2000
# with 128 x 128 local maps: 1.2 GB) every candidate's footprint is read from the maps.
WINDOW_BYTES = 256 << 20


def candidate_window(cfg: FilterConfig) -> int:
    """Side (cells) of the square of each particle's map that ``score_candidates`` reads once
    for all its candidates: a rotated local map (``FilterConfig.reach``) anywhere within
    ``reach / 2`` cells of the particle's prior mean; 0 when the windows of all particles
    would take more than ``WINDOW_BYTES``."""
    side = 2 * (cfg.reach + cfg.reach // 2) + 1
    return side if 8 * cfg.num_particles * side * side <= WINDOW_BYTES else 0


def thin_observation(obs: Observation, stride: int) -> Observation:
    """Every ``stride``-th observed cell of ``obs`` (static slicing: the valid cells stay first,
    padding keeps k = S = 0): a spatially even subset of the local map, for scoring the
    proposal's candidates as GMapping's ``lskip`` skips beams in its scan matching."""
    if stride == 1:
        return obs
    return obs._replace(index=obs.index[::stride], k=obs.k[::stride], S=obs.S[::stride])


def score_candidates(store: maps.Maps, mean: Array, chol: Array, g: Array, unknown_u: Array,
                     obs: Observation, params: FilterParams, cfg: FilterConfig) -> Array:
    """log lambda [J, K] (eq. 26 with eq. 30 / 31) of the local map at every particle's
    candidate poses m_j + C_j g_jk (``g`` [J, K, 3]), against the maps before this update
    (``candidate_scorer`` applied once)."""
    return candidate_scorer(store, mean, chol, unknown_u, obs, params, cfg)(g)


def candidate_scorer(store: maps.Maps, mean: Array, chol: Array, unknown_u: Array,
                     obs: Observation, params: FilterParams, cfg: FilterConfig) -> Score:
    """The ``Score`` of this update: candidates g [J, K, 3] (whitened, pose m_j + C_j g_jk) ->
    log lambda [J, K] against the maps before this update.

    Each particle's map is read once here, for the candidates of every stage: eq. 31's
    borrowed known cells (they do not depend on the pose) and the square of
    ``candidate_window`` cells around its prior mean; each candidate's footprint is then
    gathered from that small window. A
    candidate batch with a footprint cell outside its particle's window (a prior wider than
    the window) is read from the maps instead, as is every batch when the windows would not
    fit ``WINDOW_BYTES``, so the scores are exactly those of ``read_footprints`` at every
    candidate, whichever path is taken."""
    J = cfg.num_particles
    H, W = cfg.map_shape
    side = candidate_window(cfg)
    rows = jnp.arange(J, dtype=jnp.int32)
    borrowed = read_borrowed(store, rows, unknown_u, cfg)
    obs = thin_observation(obs, cfg.proposal_cell_stride)
    log_v = cells.log_v_obs(obs.k, obs.S)
    noise = cell_noise(obs.index, params)

    def read_maps(flat: Array, on_map: Array) -> tuple[Array, Array]:
        return maps.read(store, rows, flat, on_map, cfg)

    read_cells = read_maps
    if side:
        # the window: cells (i0 + a, j0 + b), a, b in [0, side), centred on the mean's cell
        i0 = jnp.floor((mean[:, 0] - cfg.map_origin[0]) / cfg.resolution).astype(jnp.int32)
        j0 = jnp.floor((mean[:, 1] - cfg.map_origin[1]) / cfg.resolution).astype(jnp.int32)
        i0, j0 = i0 - side // 2, j0 - side // 2
        a = jnp.arange(side, dtype=jnp.int32)
        wi = i0[:, None, None] + a[None, :, None]
        wj = j0[:, None, None] + a[None, None, :]
        on = ((wi >= 0) & (wi < H) & (wj >= 0) & (wj < W)).reshape(J, -1)
        k_win, S_win = read_maps(jnp.where(on, (wi * W + wj).reshape(J, -1), H * W), on)

        def read_cells(flat: Array, on_map: Array) -> tuple[Array, Array]:
            ri, rj = flat // W - i0[:, None], flat % W - j0[:, None]
            inside = (ri >= 0) & (ri < side) & (rj >= 0) & (rj < side)
            at = jnp.where(inside, ri * side + rj, 0)

            def from_window() -> tuple[Array, Array]:
                take = partial(jnp.take_along_axis, indices=at, axis=1)
                return (jnp.where(on_map, take(k_win), 0.0),
                        jnp.where(on_map, take(S_win), 0.0))

            return lax.cond(jnp.all(inside | ~on_map), from_window,
                            lambda: read_maps(flat, on_map))

    def one(g_k: Array) -> Array:
        pose = mean + jnp.einsum("jab,jb->ja", chol, g_k)
        return log_lambda(footprint_at(pose, obs, borrowed, read_cells, cfg), log_v, params,
                          cfg, noise)

    def score(g: Array) -> Array:
        return lax.map(one, jnp.swapaxes(g, 0, 1)).T

    return score

Score = Callable[[Array], Array]
"""Candidates g [J, K, 3] (whitened) -> their log importance factors [J, K]."""

Exponent = Callable[[Array, Array], Array]
"""(log lambda [J, K], log prior density [J, K]) of the first grid's candidates -> the
tempering exponent phi []."""


def update_exponent(log_w: Array, cfg: FilterConfig) -> Exponent:
    """The update's rule for the tempering exponent from the first grid's scores, given the
    normalised log weights ``log_w`` [J] before it: 1 with fixed tempering (the paper's beta);
    with adaptive tempering ``tempering.adaptive_exponent`` on every particle's candidates as
    one cloud weighted w_j N(g_k; 0, I) (``proposal_exponent = "prior"``), or
    ``tempering.normaliser_exponent`` on each particle's normaliser (``"normaliser"``)."""

    def exponent(log_lam: Array, log_prior: Array) -> Array:
        if cfg.tempering == "adaptive" and cfg.proposal_exponent == "normaliser":
            return tempering.normaliser_exponent(log_w, log_lam, log_prior, cfg.ess_target)
        cloud = log_w[:, None] + log_prior
        cloud = cloud - jax.nn.logsumexp(cloud)
        return tempering.exponent(cloud.reshape(-1), log_lam.reshape(-1), cfg.tempering,
                                  cfg.ess_target)

    return exponent


def quadratic_design(t: Array) -> Array:
    """Least-squares operator [10, K] that takes values at the grid points ``t`` [K, 3] to the
    coefficients of c + b.t + sum_a q_aa t_a^2 + sum_{a<b} q_ab t_a t_b."""
    x, y, z = t[:, 0], t[:, 1], t[:, 2]
    X = jnp.stack([jnp.ones_like(x), x, y, z, x * x, y * y, z * z, x * y, x * z, y * z], -1)
    return jnp.linalg.pinv(X)


def quadratic_hessian(coef: Array) -> tuple[Array, Array]:
    """Gradient at 0 [J, 3] and Hessian [J, 3, 3] of the quadratics with coefficients [J, 10]
    (``quadratic_design``'s order)."""
    b = coef[:, 1:4]
    d, xy, xz, yz = coef[:, 4:7], coef[:, 7], coef[:, 8], coef[:, 9]
    H = jnp.stack([jnp.stack([2 * d[:, 0], xy, xz], -1),
                   jnp.stack([xy, 2 * d[:, 1], yz], -1),
                   jnp.stack([xz, yz, 2 * d[:, 2]], -1)], -2)
    return b, H


def _gaussian_of_quadratic(coef: Array, span: float, spacing: float) -> tuple[Array, Array]:
    """Mean [J, 3] and covariance [J, 3, 3] of exp(quadratic) (the coefficients [J, 10] of
    ``quadratic_design``), in grid coordinates: precision P = -Hessian with its eigenvalues
    at least 1 / span^2 (a flat or convex direction gets the grid's width), the mode P^-1 b
    clipped to the grid, and a covariance never sharper than the grid resolves (precision at
    most 64 / spacing^2: a later stage, on a finer grid, sharpens it)."""
    b, H = quadratic_hessian(coef)
    vals, vecs = jnp.linalg.eigh(-H)
    vals = jnp.maximum(vals, 1.0 / span ** 2)
    mode = jnp.einsum("jab,jb,jcb,jc->ja", vecs, 1.0 / vals, vecs, b)
    vals = jnp.minimum(vals, 64.0 / spacing ** 2)
    cov = jnp.einsum("jab,jb,jcb->jac", vecs, 1.0 / vals, vecs)
    return jnp.clip(mode, -span, span), cov


def fit_proposal(score: Score, num: int, points: int, span: float, stages: int,
                 exponent: Exponent) -> tuple[Array, Array, Array]:
    """The proposal N(mu, Q) [J, 3], Cholesky factor of Q [J, 3, 3], in whitened coordinates,
    and the tempering exponent phi: the Gaussian of the quadratic fitted by least squares to
    the tempered target s = phi log lambda - |g|^2 / 2 at candidate grids (the Laplace
    approximation from points around the mode, as GMapping fits its proposal).

    Stage 1 scores ``candidate_grid(points, span)`` around the prior mean, and
    ``exponent(log_lam, log_prior)`` chooses phi from those scores; each later stage scores
    the same grid in the coordinates of the previous stage's Gaussian (centred on its mean,
    scaled by its factor), so the last fit is made where the target's mass is. An exactly
    quadratic target is fitted exactly at the first stage."""
    t, spacing = candidate_grid(points, span)
    design = quadratic_design(t)

    def stage(carry: tuple[Array, Array, Array], first: Array
              ) -> tuple[tuple[Array, Array, Array], None]:
        a, B, phi = carry
        g = a[:, None, :] + jnp.einsum("jab,kb->jka", B, t)
        log_lam = score(g)
        log_prior = -0.5 * jnp.sum(g * g, axis=-1)
        phi = lax.cond(first, lambda: exponent(log_lam, log_prior).astype(phi.dtype),
                       lambda: phi)
        s = phi * log_lam + log_prior
        finite = jnp.isfinite(s)
        floor = jnp.min(jnp.where(finite, s, jnp.inf), axis=1, keepdims=True)
        s = jnp.where(finite, s, floor)
        m, C = _gaussian_of_quadratic(s @ design.T, span, spacing)
        return (a + jnp.einsum("jab,jb->ja", B, m), B @ jnp.linalg.cholesky(C), phi), None

    # one traced stage for all (a scan, not a Python loop): the scorer is compiled once
    start = (jnp.zeros((num, 3), jnp.float32),
             jnp.broadcast_to(jnp.eye(3, dtype=jnp.float32), (num, 3, 3)),
             jnp.zeros((), jnp.float32))
    (a, B, phi), _ = lax.scan(stage, start, jnp.arange(stages) == 0)
    return a, B, phi


def _log_normal(x: Array, mu: Array, chol: Array) -> Array:
    """log N(x; mu, L L^T) for [J, 3] points, [J, 3] means and [J, 3, 3] factors."""
    z = jax.scipy.linalg.solve_triangular(chol, (x - mu)[..., None], lower=True)[..., 0]
    log_det = jnp.sum(jnp.log(jnp.abs(jnp.diagonal(chol, axis1=-2, axis2=-1))), axis=-1)
    return -0.5 * jnp.sum(z * z, axis=-1) - log_det - 1.5 * math.log(2.0 * math.pi)


class Draw(NamedTuple):
    """The informed proposal's draw at one update."""

    pose: Array            # [J, 3] drawn poses
    log_correction: Array  # [J] log N(g; 0, I) - log N(g; mu, Q): the prior over the proposal
    phi: Array             # [] the tempering exponent the proposal and the weights share


def draw(store: maps.Maps, mean: Array, cov: Array, z: Array,
         exponent: Exponent, unknown_u: Array, obs: Observation,
         params: FilterParams, cfg: FilterConfig) -> Draw:
    """Each particle's pose from its informed proposal, given standard-normal draws z [J, 3];
    ``exponent`` chooses the update's tempering exponent from the first grid's scores.

    With ``cfg.proposal_points == 1`` no candidate is scored: the proposal is the prior
    N(m_j, P_j), the correction is exactly 0 and phi is left to the update (NaN here)."""
    chol = prior_factor(cov)
    J = mean.shape[0]
    if cfg.proposal_points == 1:
        return Draw(mean + jnp.einsum("jab,jb->ja", chol, z), jnp.zeros(J, mean.dtype),
                    jnp.full((), jnp.nan, mean.dtype))

    score = candidate_scorer(store, mean, chol, unknown_u, obs, params, cfg)
    mu, q_chol, phi = fit_proposal(score, J, cfg.proposal_points, cfg.proposal_span,
                                   cfg.proposal_stages, exponent)
    g = mu + jnp.einsum("jab,jb->ja", q_chol, z)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=mean.dtype), q_chol.shape)
    correction = _log_normal(g, jnp.zeros_like(mu), eye) - _log_normal(g, mu, q_chol)
    return Draw(mean + jnp.einsum("jab,jb->ja", chol, g), correction, phi)


# The selector: what the configured proposal does at each point of the filter, chosen once.

Proposal = Callable[[FilterState, Array, Array, FilterParams], FilterState]
"""(state, u [3], standard-normal draws [J, 3], params) -> state with the particles moved: a
frame's move (``kernel.step``'s ``propose``)."""


def move_by_motion(state: FilterState, u: Array, eps: Array, params: FilterParams
                   ) -> FilterState:
    """The motion proposal's frame (a ``Proposal``): every particle moved by the motion model
    with its draws ``eps`` (eq. 24)."""
    return state._replace(pose=apply_motion(state.pose, u, eps, params.motion))


def move_by_mean(state: FilterState, u: Array, eps: Array, params: FilterParams
                 ) -> FilterState:
    """The informed proposal's frame (a ``Proposal``; ``eps`` unused): every particle moved by
    the motion model's mean, its motion covariance accumulated (``propagate_mean``); the pose
    is drawn at the next update (``ProposalRule.draw``)."""
    pose, cov = propagate_mean(state.pose, state.prior_cov, u, params.motion)
    return state._replace(pose=pose, prior_cov=cov)


def _start_by_motion(pose: Array, start_sigma: Array | None, key: Array | None
                     ) -> tuple[Array, Array | None]:
    """The motion proposal's start: the spread ``start_sigma`` drawn now from ``key``."""
    if start_sigma is None:
        return pose, None
    if key is None:
        raise ValueError("init: a start_sigma needs a PRNG key to draw the start poses")
    sigma = jnp.asarray(start_sigma, jnp.float32)
    return pose + jax.random.normal(key, pose.shape, jnp.float32) * sigma, None


def _start_by_prior(pose: Array, start_sigma: Array | None, key: Array | None
                    ) -> tuple[Array, Array | None]:
    """The informed proposal's start: the spread ``start_sigma`` not drawn but every particle's
    prior covariance, drawn at the first update together with the motion."""
    J = pose.shape[0]
    if start_sigma is None:
        return pose, jnp.zeros((J, 3, 3), jnp.float32)
    sigma = jnp.asarray(start_sigma, jnp.float32)
    return pose, jnp.broadcast_to(jnp.diag(sigma * sigma), (J, 3, 3))


class UpdateDraw(NamedTuple):
    """What a proposal does at an update, before the particles are weighed."""

    state: FilterState    # the particles at their poses for this update
    log_correction: Array  # [J] added to each log weight (0: the motion proposal)
    phi: Array | None      # [] the tempering exponent the proposal was fitted with (None: the
                           # update chooses it from the weights)


def _draw_none(state: FilterState, obs: Observation, unknown_u: Array, z: Array | None,
               params: FilterParams, cfg: FilterConfig) -> UpdateDraw:
    """The motion proposal at an update: the particles stay where the frame moved them."""
    return UpdateDraw(state, jnp.zeros((cfg.num_particles,), state.log_w.dtype), None)


def _draw_informed(state: FilterState, obs: Observation, unknown_u: Array, z: Array | None,
                   params: FilterParams, cfg: FilterConfig) -> UpdateDraw:
    """The informed proposal at an update: every particle's pose drawn from its proposal
    (``draw``, standard normals ``z`` [J, 3]), its prior covariance spent; with more than one
    candidate the exponent is the one the proposal was fitted with."""
    d = draw(state.maps, state.pose, state.prior_cov, z,
             update_exponent(state.log_w, cfg), unknown_u, obs, params, cfg)
    state = state._replace(pose=d.pose, prior_cov=jnp.zeros_like(state.prior_cov))
    return UpdateDraw(state, d.log_correction, d.phi if cfg.proposal_points > 1 else None)


class ProposalRule(NamedTuple):
    """One proposal at each point of the filter where it matters (``select``)."""

    start: Callable[[Array, Array | None, Array | None], tuple[Array, Array | None]]
    """(start poses [J, 3], start_sigma [3] or None, key or None) -> (poses, prior covariance
    [J, 3, 3] or None): ``kernel.init``."""
    move: Proposal
    """Every frame's move: ``kernel.step``'s default ``propose``."""
    draw: Callable[..., UpdateDraw]
    """(state, observation, unknown_u, z, params, cfg) -> ``UpdateDraw``: ``kernel.update``."""
    normals: bool
    """An update draws standard normals [J, 3] for it (``draws.update_noise``)."""


RULES: dict[str, ProposalRule] = {
    "motion": ProposalRule(_start_by_motion, move_by_motion, _draw_none, normals=False),
    "informed": ProposalRule(_start_by_prior, move_by_mean, _draw_informed, normals=True),
}
"""``[filter] proposal`` (``choices.PROPOSALS``) -> its rule."""


def select(cfg: FilterConfig) -> ProposalRule:
    """The rule of ``cfg.proposal``: the one place the filter decides on its proposal."""
    return RULES[cfg.proposal]
