"""Where a local map lands: each particle's footprint in its global map (paper 6.1, "rotate and
translate the observation"), the compacted observation, and what an update reads there."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from gslam_jax.rbpf import unknown
from gslam_jax.rbpf import maps
from gslam_jax.rbpf.types import FilterConfig, Observation

__all__ = ["Footprint", "compact_observation", "observation_cells", "read_footprints"]


def compact_observation(local_obs: Array, cfg: FilterConfig) -> Observation:
    """[L, L, 2] local map (k, S) -> its observed cells (``Observation``), once per update."""
    M = cfg.max_observed
    k = local_obs[..., 0].reshape(-1)
    S = local_obs[..., 1].reshape(-1)
    observed = k > 0
    index = jnp.nonzero(observed, size=M, fill_value=0)[0].astype(jnp.int32)
    count = jnp.sum(observed)
    valid = jnp.arange(M) < count
    return Observation(index, jnp.where(valid, k[index], 0.0), jnp.where(valid, S[index], 0.0),
                       jnp.maximum(count - M, 0).astype(jnp.int32))


def observation_cells(pose: Array, local_index: Array, cfg: FilterConfig) -> tuple[Array, Array]:
    """The map cell under each given local cell seen from ``pose`` (paper 6.1: "rotate and
    translate the observation"): flat map indices and whether each lies inside the map.

    Local cell (a, b) (flat index a * L + b) covers robot-frame x in [a - L/2, a - L/2 + 1)
    cells (y likewise with b); its centre is rotated by the particle's heading, translated to
    its position, and takes the map cell it falls in. Every local cell lands in exactly one map
    cell, so no observation is dropped or counted twice; off-map cells get index H*W and are
    masked, never wrapped.
    """
    H, W = cfg.map_shape
    L = cfg.local_size
    # Robot position in cells, and local cell centres in cells (small numbers: float32-safe).
    px = (pose[0] - cfg.map_origin[0]) / cfg.resolution
    py = (pose[1] - cfg.map_origin[1]) / cfg.resolution
    ca = (local_index // L).astype(jnp.float32) - (L // 2) + 0.5
    cb = (local_index % L).astype(jnp.float32) - (L // 2) + 0.5
    c, s = jnp.cos(pose[2]), jnp.sin(pose[2])
    gi = jnp.floor(px + (c * ca - s * cb)).astype(jnp.int32)
    gj = jnp.floor(py + (s * ca + c * cb)).astype(jnp.int32)
    on_map = (gi >= 0) & (gi < H) & (gj >= 0) & (gj < W)
    return jnp.where(on_map, gi * W + gj, H * W), on_map


class Footprint(NamedTuple):
    """What one update reads from the maps for a block of n particles ([n, ...] leaves)."""

    cells: Array     # [n, M] flat map index under each observed local cell (H*W off the map)
    off_map: Array   # [n] some observed local cell fell outside the map
    k_obs: Array     # [n, M] the observed cells, zero where their cell fell off the map
    S_obs: Array
    k_prior: Array   # [n, M] map statistics under the observed cells
    S_prior: Array
    k_draws: Array   # [n, unknown_samples] borrowed known cells ([n, 0] in "ignore" mode)
    S_draws: Array
    can_borrow: Array  # [n]


def read_footprints(store: maps.Maps, bits: Array, pose: Array, rows: Array,
                    unknown_u: Array, obs: Observation, cfg: FilterConfig) -> Footprint:
    """Everything the update reads from the maps of particles ``rows`` ([n]; ``pose``, ``bits``
    and ``unknown_u`` are theirs). store: the maps of all particles (``FilterState.maps``),
    read through ``maps.read``."""
    flat, on_map = jax.vmap(lambda p: observation_cells(p, obs.index, cfg))(pose)
    k_obs = jnp.where(on_map, obs.k, 0.0)
    S_obs = jnp.where(on_map, obs.S, 0.0)
    if cfg.unknown_cells == "sample":
        # unknown_samples uniform known cells; observed cell c borrows draw c mod unknown_samples
        # (see importance.log_lambda), so every unknown cell borrows a uniformly random known
        # cell (draws are shared between cells unknown_samples apart, which keeps the search
        # cost independent of the local map). Only the draws are read from the big map.
        idx, total = jax.vmap(unknown.sample_known_cells)(bits, unknown_u)
        drawn = jnp.ones(idx.shape, bool)
        kb, Sb = maps.read(store, rows, idx, drawn, cfg)
        can_borrow = total > 0
    else:
        kb = Sb = jnp.zeros((pose.shape[0], 0), jnp.float32)
        can_borrow = jnp.zeros((pose.shape[0],), bool)
    return Footprint(flat, jnp.any(~on_map & (obs.k > 0), axis=1), k_obs, S_obs,
                     *maps.read(store, rows, flat, on_map, cfg), kb, Sb, can_borrow)
