"""Where an observation lands: the map cell under each local-map cell seen from a pose (paper
6.1). Shared by every map store's update and by the window store's replay of past local maps,
so both place a local map with the same arithmetic."""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array

from gslam_jax.rbpf.types import FilterConfig

__all__ = ["observation_cells", "observation_rows_cols"]


def observation_cells(pose: Array, local_index: Array, cfg: FilterConfig,
                      lattice_heading: Array | float = 0.0) -> tuple[Array, Array]:
    """The map cell under each given local cell seen from ``pose`` (paper 6.1: "rotate and
    translate the observation"): flat map indices and whether each lies inside the map.

    Local cell (a, b) (flat index a * L + b) covers x in [a - L/2, a - L/2 + 1) cells (y
    likewise with b) on the local map's lattice, which is turned by ``lattice_heading``
    against the robot frame; its centre is rotated by the particle's heading plus that angle,
    translated to its position, and takes the map cell it falls in. Every local cell lands in
    exactly one map cell, so no observation is dropped; off-map cells get index H*W and are
    masked, never wrapped. Where the lattice lies turned against the map's (the particle's
    heading plus ``lattice_heading`` far from a multiple of 90 degrees), some map cells take
    two local cells and others none (docs/notebook/results.md, "The map frame's orientation").
    """
    H, W = cfg.map_shape
    gi, gj = observation_rows_cols(pose, local_index, cfg, lattice_heading)
    on_map = (gi >= 0) & (gi < H) & (gj >= 0) & (gj < W)
    return jnp.where(on_map, gi * W + gj, H * W), on_map


def observation_rows_cols(pose: Array, local_index: Array, cfg: FilterConfig,
                          lattice_heading: Array | float = 0.0) -> tuple[Array, Array]:
    """``observation_cells``' map row and column of each local cell, on the map or not."""
    L = cfg.local_size
    # Robot position in cells, and local cell centres in cells (small numbers: float32-safe).
    px = (pose[0] - cfg.map_origin[0]) / cfg.resolution
    py = (pose[1] - cfg.map_origin[1]) / cfg.resolution
    ca = (local_index // L).astype(jnp.float32) - (L // 2) + 0.5
    cb = (local_index % L).astype(jnp.float32) - (L // 2) + 0.5
    heading = pose[2] + lattice_heading
    c, s = jnp.cos(heading), jnp.sin(heading)
    gi = jnp.floor(px + (c * ca - s * cb)).astype(jnp.int32)
    gj = jnp.floor(py + (s * ca + c * cb)).astype(jnp.int32)
    return gi, gj
