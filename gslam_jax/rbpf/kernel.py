"""The filter kernel (paper 6.1-6.2): init, predict, update, resample, one frame, the scan.

One frame (``step``) is:

* a proposal at every frame: sample the motion model (eqs. 1-3, 24), or with the informed
  proposal move by its mean and draw at the update (``proposal.select`` decides, once), each
  particle with its own factor on the noise where the state carries one
  (``FilterState.noise_scale``, ``[motion] noise_spread``);
* at frames that carry a local map, ``update``: for each particle, the log-gamma importance
  factors of the observed cells against the map cells under them (eq. 26) and their tempered
  combination (eq. 30 or 31), in blocks of particles sized for the cache on a CPU
  (``FilterConfig.update_block``); the local map scatter-added into each particle's map (the
  conjugate update, eq. 14); the weights multiplied (eq. 27) and normalised;
* then ``resample`` when the ESS (eq. 23) drops below ``resample_ratio * J``.

The proposal and the resampler are arguments of ``step``, so the tuner's Scibior-Wood
estimator (``tuning``) runs this very frame with its stop-gradient versions of both. The whole
Run is a ``lax.scan`` of ``step`` (``scan_frames``, ``run_filter``); poses and resampling
ancestors are kept per frame so the best particle's full path survives resampling
(``paths``). Random numbers come from ``draws`` (``motion_noise``, ``update_noise``) so
that another implementation can be driven with exactly the same draws. The maps are touched only
through ``rbpf.maps`` (the map-store seam): nothing here knows which store holds them.
"""

from __future__ import annotations

import math
from functools import partial
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array, lax

from gslam_jax.rbpf import cells, maps, proposal, resampling, tempering
from gslam_jax.rbpf.draws import frame_keys, motion_noise, update_noise
from gslam_jax.rbpf.motion import apply_motion, particle_scales, scaled
from gslam_jax.rbpf.proposal import Proposal
from gslam_jax.rbpf.paths import backtrack_path, weighted_mean_pose
from gslam_jax.rbpf.footprint import compact_observation, read_footprints
from gslam_jax.rbpf.importance import cell_noise, log_lambda
from gslam_jax.rbpf.types import (FilterConfig, FilterParams, FilterState, Observation,
                                  RunOutput, StepInfo, UpdateInfo, UpdateNoise)

__all__ = ["Proposal", "Resampler", "init", "predict", "update", "ancestors", "resample",
           "observe", "step", "scan_frames", "run_filter", "best_slot", "mean_noise_scale"]

Resampler = Callable[[FilterState, Array, FilterConfig], tuple[FilterState, Array, Array]]
"""(state, uniforms [J], cfg) -> (state, ancestors [J], resampled []): ESS-gated resampling."""


def init(cfg: FilterConfig, start_pose: Array | None = None,
         prior_map: tuple[Array, Array] | None = None, key: Array | None = None,
         start_sigma: Array | None = None) -> FilterState:
    """All particles at ``start_pose`` with equal weights and empty maps (``maps.init``).

    Map reuse: ``prior_map`` = (k, S) [H, W] on the filter's grid is every particle's map at
    the start (the maps are extended from it by eq. 14), and with ``start_sigma`` [3] (x, y,
    heading standard deviations) the particles start at ``start_pose`` + N(0, diag(sigma^2)),
    drawn from ``key``; a sigma of None draws nothing (every particle at ``start_pose``).
    With the "informed" proposal that spread is not drawn here but starts every particle's
    prior covariance, so that the first update draws the start together with the motion,
    from the map's score times that prior (``proposal.select``): the same prior, drawn where
    the prior map agrees with the first local map."""
    cfg.validate()
    J = cfg.num_particles
    start = (jnp.zeros(3, jnp.float32) if start_pose is None
             else jnp.asarray(start_pose, jnp.float32))
    pose, cov = proposal.select(cfg).start(jnp.broadcast_to(start, (J, 3)), start_sigma, key)
    noise = particle_scales(J, cfg.noise_spread) if cfg.noise_spread > 1 else None
    return FilterState(pose=pose, log_w=jnp.full((J,), -math.log(J), jnp.float32),
                       maps=maps.init(cfg, prior_map), best=jnp.int32(0), prior_cov=cov,
                       noise_scale=noise)


def predict(pose: Array, u: Array, eps: Array, params: FilterParams) -> Array:
    """Prediction step (eq. 24) for all particles, given their standard-normal draws."""
    return apply_motion(pose, u, eps, params.motion)


class _Weighed(NamedTuple):
    maps: maps.Maps  # the maps after eq. 14
    log_lam: Array   # [J] log importance factors (eqs. 26, 30 / 31) against the old maps
    off_map: Array   # [J] some observed local cell fell outside the map


def _weigh_block(w: _Weighed, j0: Array, n: int, state: FilterState, obs: Observation,
                 log_v: Array, noise: Array | None, unknown_u: Array, params: FilterParams,
                 cfg: FilterConfig) -> _Weighed:
    """Particles j0 .. j0+n-1: read their footprints, weigh them, add the local map."""
    rows = j0 + jnp.arange(n, dtype=jnp.int32)
    take = partial(lax.dynamic_slice_in_dim, start_index=j0, slice_size=n)
    f = read_footprints(w.maps, take(state.pose), rows, take(unknown_u), obs, cfg)
    log_lam = log_lambda(f, log_v, params, cfg, noise)
    new = w.maps
    if cfg.update_map:
        # Write only after every read of these maps (the known-cell draws included): the
        # target cells are made to depend on the weights by a min() that never changes them
        # (cells <= H*W). Without that ordering XLA copies the whole maps before the update.
        after = (jnp.sum(log_lam) > 0).astype(jnp.int32)
        cells_ = jnp.minimum(f.cells, cfg.map_shape[0] * cfg.map_shape[1] + after)
        new = maps.write(new, rows, cells_, obs.k, obs.S, cfg)
    put = partial(lax.dynamic_update_slice_in_dim, start_index=j0, axis=0)
    return _Weighed(new, put(w.log_lam, log_lam), put(w.off_map, f.off_map))


def _weigh_and_write(state: FilterState, obs: Observation, unknown_u: Array,
                     params: FilterParams, cfg: FilterConfig) -> _Weighed:
    """Eq. 26 weights of every particle against its map, and eq. 14 into that map, one block
    of ``cfg.update_block`` particles at a time (see ``FilterConfig.particle_block``)."""
    J = cfg.num_particles
    B = cfg.update_block
    w = _Weighed(state.maps, jnp.zeros((J,), state.log_w.dtype), jnp.zeros((J,), bool))
    # log v and the measurement variance of each observed cell are shared by every particle:
    # computed once, not J times.
    block = partial(_weigh_block, state=state, obs=obs, log_v=cells.log_v_obs(obs.k, obs.S),
                    noise=cell_noise(obs.index, params), unknown_u=unknown_u, params=params,
                    cfg=cfg)
    full, tail = divmod(J, B)
    if full == 1:
        w = block(w, jnp.int32(0), B)
    else:
        w = lax.fori_loop(0, full, lambda b, w: block(w, b * B, B), w)
    if tail:
        w = block(w, jnp.int32(full * B), tail)
    return w


def best_slot(log_w: Array, ancestors: Array) -> Array:
    """Slot of the highest-weight particle. ``log_w`` [J] are the normalised weights before the
    resampling that put particle ``ancestors[i]`` into slot i (the identity when none did).
    After a resampling the weights are all equal, so the choice is made on the weights before
    it; if the best particle left no offspring, this is the slot of the best one that did."""
    return jnp.argmax(log_w[ancestors]).astype(jnp.int32)


def update(state: FilterState, local_obs: Array, unknown_u: Array, params: FilterParams,
           cfg: FilterConfig, proposal_z: Array | None = None,
           lattice_heading: Array | float = 0.0) -> tuple[FilterState, UpdateInfo]:
    """Weigh, write, normalise: eq. 26 with eq. 30 / 31 against each particle's map, eq. 14
    into it, the weights multiplied (eq. 27; with ``cfg.tempering == "adaptive"`` the log
    factors are first scaled by ``tempering.adaptive_exponent``) and normalised. No resampling
    (``resample``).

    The proposal's rule (``proposal.select``) draws the poses first: with ``cfg.proposal ==
    "informed"`` each particle's from its informed proposal (standard normals ``proposal_z``
    [J, 3]), its weight taking the proposal's exact correction, and with more than one
    candidate the exponent the proposal was fitted with (chosen from the scores at the prior
    means).

    local_obs: [L, L, 2] observation (k, S) of the local map, robot-centred, on a lattice
    turned by ``lattice_heading`` against the robot (``Run.lattice_headings``); unknown_u:
    ``UpdateNoise.unknown_u``. The state's ``best`` becomes the highest-weight particle.
    """
    J = cfg.num_particles
    obs = compact_observation(local_obs, cfg, lattice_heading)
    state, correction, fitted_phi = proposal.select(cfg).draw(state, obs, unknown_u, proposal_z,
                                                              params, cfg)
    w = _weigh_and_write(state, obs, unknown_u, params, cfg)
    phi = (tempering.exponent(state.log_w, w.log_lam, cfg.tempering, cfg.ess_target)
           if fitted_phi is None else fitted_phi)
    unnorm = state.log_w + phi * w.log_lam + correction
    log_lik = jax.nn.logsumexp(unnorm)  # log sum_j w_j lambda_j: the evidence increment
    log_w = unnorm - log_lik
    new_maps = maps.finish_update(w.maps, state.pose, cfg, obs)
    best = best_slot(log_w, jnp.arange(J, dtype=jnp.int32))
    info = UpdateInfo(ess=resampling.ess(log_w), log_lik=log_lik,
                      extent_violations=jnp.sum(w.off_map).astype(jnp.int32),
                      empty_obs=~jnp.any(obs.k > 0), dropped_cells=obs.dropped,
                      exponent=phi)
    return state._replace(log_w=log_w, maps=new_maps, best=best), info


def ancestors(log_w: Array, u: Array, cfg: FilterConfig) -> Array:
    """Ancestor indices by ``cfg.resampler`` from normalised log weights and uniforms [J],
    arranged so that survivors keep their slots (``resampling.keep_in_place``)."""
    return resampling.keep_in_place(resampling.resample(cfg.resampler, jnp.exp(log_w), u))


def _equal_weights(log_w: Array) -> Array:
    return jnp.full(log_w.shape, -math.log(log_w.shape[0]), log_w.dtype)


def resample(state: FilterState, u: Array, cfg: FilterConfig,
             new_log_w: Callable[[Array], Array] = _equal_weights
             ) -> tuple[FilterState, Array, Array]:
    """ESS-gated resampling (eq. 23; a ``Resampler``): when ESS < ``resample_ratio * J``
    (``resampling.below_threshold``: a tie within float rounding resamples), particles are
    drawn by ``ancestors`` and take their poses, noise factors and maps (``maps.resample``:
    dense maps copied over the rows written so far, shared page tables gathered). Returns
    (state, ancestors [J], resampled []).

    The choice and the ancestors use the weights' values only (stop-gradient); the new log
    weights are ``new_log_w(log_w[ancestors])``: equal by default (the paper's filter); the
    tuner passes the Scibior-Wood weights, which keep the ancestry's gradient. ``best`` stays
    the particle that was best before resampling (``best_slot``).
    """
    J = cfg.num_particles
    lw = lax.stop_gradient(state.log_w)
    do = resampling.below_threshold(lw, cfg.resample_ratio)

    def yes(s: FilterState) -> tuple[FilterState, Array]:
        anc = ancestors(lw, u, cfg)

        def take(x: Array | None) -> Array | None:
            return None if x is None else jnp.take(x, anc, axis=0)

        return s._replace(maps=maps.resample(s.maps, anc), pose=take(s.pose),
                          log_w=new_log_w(take(s.log_w)), prior_cov=take(s.prior_cov),
                          noise_scale=take(s.noise_scale)), anc

    def keep(s: FilterState) -> tuple[FilterState, Array]:
        return s, jnp.arange(J, dtype=jnp.int32)

    new, anc = lax.cond(do, yes, keep, state)
    return new._replace(best=best_slot(lw, anc)), anc, do


def observe(state: FilterState, local_obs: Array, noise: UpdateNoise, params: FilterParams,
            cfg: FilterConfig, resampler: Resampler = resample,
            lattice_heading: Array | float = 0.0) -> tuple[FilterState, StepInfo]:
    """``update`` with ``noise.unknown_u``, then ``resampler`` with ``noise.resample_u``."""
    state, upd = update(state, local_obs, noise.unknown_u, params, cfg, noise.proposal_z,
                        lattice_heading)
    state, anc, resampled = resampler(state, noise.resample_u, cfg)
    return state, StepInfo(pose=state.pose, ancestors=anc, best=state.best, log_w=state.log_w,
                           ess=upd.ess, resampled=resampled, updated=jnp.bool_(True),
                           log_lik=upd.log_lik, extent_violations=upd.extent_violations,
                           empty_obs=upd.empty_obs, dropped_cells=upd.dropped_cells,
                           map_status=maps.status(state.maps), exponent=upd.exponent,
                           map_free=maps.free_tiles(state.maps),
                           noise_scale=mean_noise_scale(state))


def _no_update_info(state: FilterState, cfg: FilterConfig) -> StepInfo:
    J = cfg.num_particles
    return StepInfo(pose=state.pose, ancestors=jnp.arange(J, dtype=jnp.int32), best=state.best,
                    log_w=state.log_w,
                    ess=resampling.ess(state.log_w), resampled=jnp.bool_(False),
                    updated=jnp.bool_(False), log_lik=jnp.float32(0.0),
                    extent_violations=jnp.int32(0), empty_obs=jnp.bool_(False),
                    dropped_cells=jnp.int32(0), map_status=maps.status(state.maps),
                    exponent=jnp.float32(1.0), map_free=maps.free_tiles(state.maps),
                    noise_scale=mean_noise_scale(state))


def mean_noise_scale(state: FilterState) -> Array:
    """The particles' factor on the motion stds, their weighted geometric mean (1: none)."""
    if state.noise_scale is None:
        return jnp.float32(1.0)
    return jnp.exp(jnp.sum(jnp.exp(state.log_w) * jnp.log(state.noise_scale)))


def step(key: Array, state: FilterState, u: Array, local_obs: Array | None,
         params: FilterParams, cfg: FilterConfig, has_obs: Array | bool = True, *,
         propose: Proposal | None = None, resampler: Resampler = resample,
         lattice_heading: Array | float = 0.0,
         fallback: Array | bool = False) -> tuple[FilterState, StepInfo]:
    """One frame, the filter's only one: ``propose`` (predict, eq. 24), then, if the frame has
    a local map, ``observe`` (update, then ``resampler``).

    ``local_obs`` None: no update (a Python-level choice); else ``has_obs`` says whether the
    frame has one: True (Python) updates, a traced bool chooses under ``lax.cond``. The key is
    split once into the motion draws and the update's draws (``update_noise``). ``propose``
    None: the configured proposal's move (``proposal.select``: ``move_by_motion``, eq. 24, or
    ``move_by_mean`` for "informed"). ``lattice_heading``: the local map's (``update``). ``fallback``: the
    control came from the fallback odometry, so the motion noise's stds are
    ``params.motion.fallback_scale`` times the VO's (``scaled``); a Python False leaves the
    frame's motion model untouched (no scaling in the program). A state with particle noise
    scales (``FilterState.noise_scale``) moves each particle with its own.
    """
    if propose is None:
        propose = proposal.select(cfg).move
    k_motion, k_update = jax.random.split(key)
    scale = state.noise_scale  # [J] or None
    if fallback is not False:
        on_fallback = jnp.where(fallback, params.motion.fallback_scale, 1.0)
        scale = on_fallback if scale is None else scale * on_fallback
    frame_params = params if scale is None else params._replace(
        motion=scaled(params.motion, scale))
    state = propose(state, u, motion_noise(k_motion, cfg), frame_params)
    if local_obs is None or has_obs is False:
        return state, _no_update_info(state, cfg)

    def observe_frame(s: FilterState) -> tuple[FilterState, StepInfo]:
        return observe(s, local_obs, update_noise(k_update, cfg), params, cfg, resampler,
                       lattice_heading)

    if has_obs is True:
        return observe_frame(state)
    return lax.cond(has_obs, observe_frame, lambda s: (s, _no_update_info(s, cfg)), state)


def _summaries(info: StepInfo) -> tuple[Array, Array]:
    return info.pose[info.best], weighted_mean_pose(jnp.exp(info.log_w), info.pose)


@partial(jax.jit, static_argnames=("cfg",), donate_argnums=(0,))
def scan_frames(state: FilterState, keys: Array, controls: Array, obs_index: Array,
                local_obs: Array, params: FilterParams, cfg: FilterConfig,
                lattice_headings: Array | None = None, fallback: Array | None = None
                ) -> tuple[FilterState, tuple[StepInfo, Array, Array]]:
    """``lax.scan`` of ``step`` over frames (update where obs_index >= 0).

    keys [T], controls [T, 3], obs_index [T] (index into local_obs or -1), local_obs
    [M, L, L, 2] observations (k, S) from ``cells.obs_from_stats`` with M >= 1,
    lattice_headings [M] (``Run.lattice_heading_array``; None: all 0, the robot's axes),
    fallback [T] bool: the frame's control came from the fallback odometry (``step``; None:
    none did, or the fallback is weighed as VO).
    Returns the final state and per-frame (StepInfo, best pose, weighted-mean pose).
    ``state`` is donated: the maps are updated in its buffers, so do not use it afterwards
    (pass ``jax.tree.map(jnp.copy, state)`` to keep it).
    """

    def frame(state, xs):
        k, u, idx = xs[:3]
        m = jnp.maximum(idx, 0)
        heading = 0.0 if lattice_headings is None else lattice_headings[m]
        state, info = step(k, state, u, local_obs[m], params, cfg, idx >= 0,
                           lattice_heading=heading,
                           fallback=False if fallback is None else xs[3])
        best, mean = _summaries(info)
        return state, (info, best, mean)

    flags = () if fallback is None else (fallback,)
    return lax.scan(frame, state, (keys, controls, obs_index) + flags)


@partial(jax.jit, static_argnames=("cfg",))
def run_filter(key: Array, params: FilterParams, controls: Array, obs_index: Array,
               local_obs: Array, cfg: FilterConfig, start_pose: Array | None = None,
               lattice_headings: Array | None = None,
               fallback: Array | None = None) -> RunOutput:
    """The whole filter in one jitted call (see ``scan_frames``); vmappable and differentiable
    in ``params``."""
    state = init(cfg, start_pose)
    final, (infos, best, mean) = scan_frames(
        state, frame_keys(key, controls.shape[0]), controls, obs_index, local_obs, params, cfg,
        lattice_headings, fallback)
    path = backtrack_path(infos.pose, infos.ancestors, final.best)
    return RunOutput(final, infos, best, mean, path)
