"""Each particle's footprint in its global map (where a local map lands, ``placement``), the
compacted observation, and what an update reads there."""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from gslam_jax.rbpf import maps
from gslam_jax.rbpf.placement import observation_cells
from gslam_jax.rbpf.types import FilterConfig, Observation

__all__ = ["Footprint", "Borrowed", "compact_observation", "read_borrowed", "footprint_at",
           "read_footprints"]


def compact_observation(local_obs: Array, cfg: FilterConfig,
                        lattice_heading: Array | float = 0.0) -> Observation:
    """[L, L, 2] local map (k, S) on a lattice turned by ``lattice_heading`` against the robot
    (``Run.lattice_headings``) -> its observed cells (``Observation``), once per update."""
    M = cfg.max_observed
    k = local_obs[..., 0].reshape(-1)
    S = local_obs[..., 1].reshape(-1)
    observed = k > 0
    index = jnp.nonzero(observed, size=M, fill_value=0)[0].astype(jnp.int32)
    count = jnp.sum(observed)
    valid = jnp.arange(M) < count
    return Observation(index, jnp.where(valid, k[index], 0.0), jnp.where(valid, S[index], 0.0),
                       jnp.maximum(count - M, 0).astype(jnp.int32),
                       jnp.asarray(lattice_heading, jnp.float32))


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


class Borrowed(NamedTuple):
    """Eq. 31's known cells drawn for unknown cells, for a block of n particles."""

    k: Array           # [n, unknown_samples] ([n, 0] in "ignore" mode)
    S: Array
    can_borrow: Array  # [n] the particle's map has a known cell


def read_borrowed(store: maps.Maps, rows: Array, unknown_u: Array, cfg: FilterConfig
                  ) -> Borrowed:
    """The known cells that the unknown cells of particles ``rows`` borrow (eq. 31, "sample"
    mode; empty otherwise). They depend on the particle's map and uniforms only, not on its
    pose, so every candidate pose of the informed proposal shares them."""
    n = rows.shape[0]
    if cfg.unknown_cells != "sample":
        empty = jnp.zeros((n, 0), jnp.float32)
        return Borrowed(empty, empty, jnp.zeros((n,), bool))
    # unknown_samples uniform known cells; observed cell c borrows draw c mod unknown_samples
    # (see importance.log_lambda), so every unknown cell borrows a uniformly random known
    # cell (draws are shared between cells unknown_samples apart, which keeps the search
    # cost independent of the local map). Only the draws are read from the big map.
    idx, total = maps.sample_known(store, rows, unknown_u, cfg)
    kb, Sb = maps.read(store, rows, idx, jnp.ones(idx.shape, bool), cfg)
    return Borrowed(kb, Sb, total > 0)


def footprint_at(pose: Array, obs: Observation, borrowed: Borrowed,
                 read_cells: Callable[[Array, Array], tuple[Array, Array]],
                 cfg: FilterConfig) -> Footprint:
    """The footprint of poses [n, 3], the map statistics under it read by ``read_cells``
    (flat cells [n, M], on_map [n, M] -> (k, S) [n, M], 0 off the map)."""
    flat, on_map = jax.vmap(lambda p: observation_cells(p, obs.index, cfg,
                                                        obs.lattice_heading))(pose)
    return Footprint(flat, jnp.any(~on_map & (obs.k > 0), axis=1),
                     jnp.where(on_map, obs.k, 0.0), jnp.where(on_map, obs.S, 0.0),
                     *read_cells(flat, on_map), borrowed.k, borrowed.S, borrowed.can_borrow)


def read_footprints(store: maps.Maps, pose: Array, rows: Array, unknown_u: Array,
                    obs: Observation, cfg: FilterConfig) -> Footprint:
    """Everything the update reads from the maps of particles ``rows`` ([n]; ``pose`` and
    ``unknown_u`` are theirs). store: the maps of all particles (``FilterState.maps``),
    read through ``maps.read`` and ``maps.sample_known``."""
    borrowed = read_borrowed(store, rows, unknown_u, cfg)
    return footprint_at(pose, obs, borrowed,
                        lambda flat, on_map: maps.read(store, rows, flat, on_map, cfg), cfg)
