"""The alignment score's chance baseline (``gridmap.score.reference_level``): for a map with
fewer known cells than the table's sample, the mean and variance of eq. 26 over exactly its
known cells, and one compiled table for maps of any size."""

from __future__ import annotations

import numpy as np
from jax import enable_x64

from gslam_jax.gridmap import GridMap, score
from gslam_jax.rbpf import cells


def _map(known: int, seed: int) -> GridMap:
    rng = np.random.default_rng(seed)
    k = np.zeros(40 * 40)
    k[rng.choice(k.size, known, replace=False)] = rng.integers(1, 40, known)
    S = k * rng.gamma(2.0, 0.01, k.size)
    return GridMap(k.reshape(40, 40), S.reshape(40, 40), (0.0, 0.0), 0.2)


def test_chance_tables_of_a_small_map_are_over_its_own_known_cells() -> None:
    a = _map(300, seed=0)  # under the 2048 samples: every known cell, padded
    max_dof, points = 8, 16
    lvl = score.reference_level(a, 1, pad=2, max_dof=max_dof, log_v_range=(-6.0, -2.0),
                                points=points)
    k, S = score.temper(a.k, a.S, max_dof)
    ka, Sa = k[k > 0], S[k > 0]
    grid = np.asarray(lvl.log_v_grid, np.float64)
    with enable_x64(True):  # eq. 26 in float64, the general (non-integer) form
        kb = np.arange(1, max_dof + 1, dtype=np.float64)[:, None, None]
        Sb = kb * np.exp(grid)[None, :, None]
        lam = np.asarray(cells.log_predictive(*np.broadcast_arrays(kb, Sb, ka[None, None],
                                                                   Sa[None, None])))
    np.testing.assert_allclose(lvl.base_mean[1:], lam.mean(axis=2), rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(lvl.base_var[1:], lam.var(axis=2), rtol=1e-3, atol=1e-3)


def test_maps_of_different_sizes_share_one_compiled_chance_table() -> None:
    score.chance_tables.clear_cache()
    for known, seed in ((120, 1), (700, 2), (1500, 3)):
        score.reference_level(_map(known, seed), 1, pad=2, max_dof=8, log_v_range=(-6.0, -2.0))
    assert score.chance_tables._cache_size() == 1
