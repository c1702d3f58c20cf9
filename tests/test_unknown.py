"""Known-cell sampler: bitmasks against brute force, draws uniform over known cells."""

import jax
import jax.numpy as jnp
import numpy as np
from scipy import stats

from gslam_jax.rbpf import unknown


def test_pack_known_bits_match_brute_force():
    rng = np.random.default_rng(0)
    known = rng.random((16, 24)) < 0.4
    bits = np.asarray(unknown.pack_known(jnp.asarray(known)))
    for bi in range(2):
        for bj in range(3):
            block = known[8 * bi:8 * bi + 8, 8 * bj:8 * bj + 8].reshape(-1)
            word = int(bits[bi, bj, 0]) | (int(bits[bi, bj, 1]) << 32)
            assert [(word >> p) & 1 for p in range(64)] == block.astype(int).tolist()


def test_draws_are_uniform_over_known_cells():
    rng = np.random.default_rng(1)
    known = rng.random((32, 32)) < 0.1
    bits = unknown.pack_known(jnp.asarray(known))
    u = jax.random.uniform(jax.random.key(0), (200_000,))
    idx, total = jax.jit(unknown.sample_known_cells)(bits, u)
    idx = np.asarray(idx)
    assert int(total) == known.sum()
    assert known.reshape(-1)[idx].all()  # only known cells are drawn
    counts = np.bincount(idx, minlength=known.size)[known.reshape(-1)]
    assert counts.min() > 0
    assert stats.chisquare(counts).pvalue > 1e-3


def test_rank_order_is_block_row_major():
    """Rank r maps to the r-th known cell in (block row-major, then bit) order."""
    rng = np.random.default_rng(2)
    known = rng.random((16, 16)) < 0.3
    order = [bi * 8 * 16 + r * 16 + bj * 8 + c
             for bi in range(2) for bj in range(2) for r in range(8) for c in range(8)
             if known[8 * bi + r, 8 * bj + c]]
    n = len(order)
    u = (np.arange(n) + 0.5) / n
    idx, _ = unknown.sample_known_cells(unknown.pack_known(jnp.asarray(known)), jnp.asarray(u, jnp.float32))
    assert np.asarray(idx).tolist() == order
