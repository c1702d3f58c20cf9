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
    idx, _ = unknown.sample_known_cells(unknown.pack_known(jnp.asarray(known)),
                                        jnp.asarray(u, jnp.float32))
    assert np.asarray(idx).tolist() == order


def test_segments_draw_the_cells_of_the_whole_map_sampler():
    """``sample_by_segments`` over ``segment_counts`` gives, for every uniform, the cell that
    ``sample_known_cells`` gives from the whole map's bits: maps 7 blocks wide (the last
    segment padded), sparse, dense and empty."""
    rng = np.random.default_rng(3)
    u = jnp.asarray(np.concatenate([[0.0, np.nextafter(np.float32(1), np.float32(0))],
                                    rng.random(998)]), jnp.float32)
    for density in (0.0, 0.02, 0.5):
        known = rng.random((40, 56)) < density
        bits = unknown.pack_known(jnp.asarray(known))
        seg = unknown.segment_counts(bits)
        assert seg.shape == (5, 2) and int(seg.sum()) == known.sum()

        def words(row, col, bits=bits):
            block = col[:, None] * unknown.SEGMENT + jnp.arange(unknown.SEGMENT)
            w = bits[row[:, None], jnp.minimum(block, bits.shape[1] - 1)]
            return jnp.where((block < bits.shape[1])[..., None], w, jnp.uint32(0))

        got, total = unknown.sample_by_segments(seg, words, u, 56)
        want, want_total = unknown.sample_known_cells(bits, u)
        assert int(total) == int(want_total) == known.sum()
        if known.any():
            np.testing.assert_array_equal(np.asarray(got), np.asarray(want))


def test_the_sampler_benchmark_runs_and_finds_the_same_cells(capsys):
    """``experiments.known_cell_sampler`` at a CI size: both stores' segment samplers draw
    the whole-map scan's cells (it exits 1 otherwise) and it prints its figures."""
    from experiments import known_cell_sampler

    assert known_cell_sampler.main(["--map", "64", "104", "--particles", "3", "--density",
                                    "0.1", "--samples", "32", "--repeats", "1"]) == 0
    out = capsys.readouterr().out
    assert out.count("same cells: True") == 2 and "# jax" in out
