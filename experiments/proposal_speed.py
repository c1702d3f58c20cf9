"""What the informed proposal's scoring costs: one read of each particle's map window for all
its candidates (``proposal.score_candidates``) against reading every candidate's footprint from
the maps (``read_footprints`` per candidate, as before), and the whole informed update against
the motion proposal's, in one process on synthetic maps (``gslam bench``'s state: particles
scattered 1 m around the map centre, maps filled by a few updates first).

    python -m experiments.proposal_speed --particles 200 --local 64 --map 640 \
        [--cell-stride 1 4 8]

With ``--cell-stride`` values the informed update is also timed at each
``[filter] proposal_cell_stride`` (the candidates scored on every n-th observed cell).
Prints the machine and versions, milliseconds per call (best of --repeats) and the ratios.
"""

from __future__ import annotations

import argparse
import json
import math
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from gslam_jax import choices, rbpf
from gslam_jax.app.bench import bench_config, synthetic_local_map, synthetic_state
from gslam_jax.driver.machine import environment
from gslam_jax.rbpf import cells, proposal
from gslam_jax.rbpf.footprint import compact_observation, read_footprints
from gslam_jax.rbpf.importance import log_lambda


def score_per_candidate(store, mean, chol, g, unknown_u, obs, params, cfg):
    """The reference: every candidate's footprint and eq. 31 draws read from the maps."""
    J = cfg.num_particles
    rows = jnp.arange(J, dtype=jnp.int32)
    log_v = cells.log_v_obs(obs.k, obs.S)

    def one(g_k):
        pose = mean + jnp.einsum("jab,jb->ja", chol, g_k)
        return log_lambda(read_footprints(store, pose, rows, unknown_u, obs, cfg), log_v,
                          params, cfg)

    return lax.map(one, jnp.swapaxes(g, 0, 1)).T


def best_seconds(fn, *args, repeats: int):
    """Best wall time of ``repeats`` calls of fn(*args) after one warm-up call, and its output."""
    out = jax.block_until_ready(fn(*args))
    best = math.inf
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t)
    return best, out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--particles", type=int, default=200)
    ap.add_argument("--local", type=int, default=64)
    ap.add_argument("--map", type=int, default=640)
    ap.add_argument("--mode", default="sample", choices=choices.UNKNOWN_CELLS)
    ap.add_argument("--store", default="dense", choices=("dense", "shared"))
    ap.add_argument("--prior-std", type=float, default=0.2,
                    help="position std (m) of the particles' accumulated prior")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--cell-stride", type=int, nargs="+", default=[],
                    help="proposal_cell_stride values to time the informed update at as well "
                    "(the config's own, 1, is timed as ms_update_informed)")
    args = ap.parse_args(argv)

    J, L, side = args.particles, args.local, args.map
    rng = np.random.default_rng(0)
    cfg = bench_config(J, L, side, args.mode, store=args.store)._replace(
        proposal="informed").validate()
    local = synthetic_local_map(rng, L)
    params = rbpf.FilterParams()
    noise = rbpf.update_noise(jax.random.key(0), cfg)
    state = synthetic_state(cfg._replace(proposal="motion"), rng)
    warm = jax.jit(lambda s: rbpf.update(s, local, noise.unknown_u, params,
                                         cfg._replace(proposal="motion"))[0])
    for _ in range(3):  # some known cells under every footprint
        state = warm(state._replace(pose=state.pose + 0.3))
    var = jnp.asarray([args.prior_std ** 2, args.prior_std ** 2, 1e-3], jnp.float32)
    cov = jnp.broadcast_to(jnp.diag(var), (J, 3, 3))
    state = state._replace(prior_cov=cov)
    obs = compact_observation(local, cfg)
    chol = proposal.prior_factor(cov)
    grid, _ = proposal.candidate_grid(cfg.proposal_points, cfg.proposal_span)
    g = jnp.broadcast_to(grid, (J,) + grid.shape)

    def timed(score):
        fn = jax.jit(lambda s: score(s.maps, s.pose, chol, g, noise.unknown_u, obs, params, cfg))
        sec, out = best_seconds(fn, state, repeats=args.repeats)
        return sec, np.asarray(out)

    sec_window, windowed = timed(proposal.score_candidates)
    sec_each, each = timed(score_per_candidate)
    z = jax.random.normal(jax.random.key(1), (J, 3))
    informed = jax.jit(lambda s: rbpf.update(s, local, noise.unknown_u, params, cfg, z)[0])
    motion = jax.jit(lambda s: rbpf.update(s._replace(prior_cov=None), local, noise.unknown_u,
                                           params, cfg._replace(proposal="motion"))[0])
    sec_informed, _ = best_seconds(informed, state, repeats=args.repeats)
    sec_motion, _ = best_seconds(motion, state, repeats=args.repeats)
    by_stride = {}
    for stride in args.cell_stride:
        c = cfg._replace(proposal_cell_stride=stride).validate()
        fn = jax.jit(lambda s, c=c: rbpf.update(s, local, noise.unknown_u, params, c, z)[0])
        by_stride[stride] = 1e3 * best_seconds(fn, state, repeats=args.repeats)[0]
    K = grid.shape[0]
    result = {
        "environment": environment(), "particles": J, "local": L, "map": side,
        "mode": args.mode, "store": args.store, "candidates_per_stage": K,
        "stages": cfg.proposal_stages, "window": proposal.candidate_window(cfg),
        # footprint cells on a cell border may round to either side in different XLA fusions
        "candidates_differing": int(np.sum(~np.isclose(windowed, each, rtol=1e-5, atol=1e-4))),
        "candidates": int(windowed.size),
        "ms_score_windowed": 1e3 * sec_window, "ms_score_per_candidate": 1e3 * sec_each,
        "speedup_windowed": sec_each / sec_window,
        "ms_update_informed": 1e3 * sec_informed, "ms_update_motion": 1e3 * sec_motion,
        "informed_over_motion": sec_informed / sec_motion,
        "ms_update_informed_by_cell_stride": by_stride,
        "informed_over_motion_by_cell_stride": {k: v / (1e3 * sec_motion)
                                                for k, v in by_stride.items()},
    }
    print(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
