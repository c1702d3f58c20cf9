"""Points -> local-map statistics: brute force binning, range gate, overhang removal."""

import numpy as np

from gslam_jax.vo.localmap import LocalMapBuilder, LocalMapParams, points_to_stats, range_gate


def test_binning_matches_brute_force():
    p = LocalMapParams(resolution=0.5, cells=8, min_height=-1.0, max_height=1.0)
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-3, 3, 500), rng.uniform(-3, 3, 500), rng.normal(0, 0.8, 500)])
    stats, dropped = points_to_stats(pts, p)
    ref = np.zeros((8, 8, 3))
    out = 0
    for x, y, z in pts:
        if not -1.0 <= z <= 1.0:
            continue
        i, j = int(np.floor(x / 0.5)) + 4, int(np.floor(y / 0.5)) + 4
        if 0 <= i < 8 and 0 <= j < 8:
            ref[i, j] += [1, z, z * z]
        else:
            out += 1
    np.testing.assert_allclose(stats, ref)
    assert dropped == out


def test_overhang_removed_and_range_gated():
    p = LocalMapParams(resolution=0.2, cells=100, max_height=2.0, max_range=5.0)
    pts = np.array([[1.0, 0.0, 0.1], [1.0, 0.0, 3.5], [6.0, 0.0, 0.0]])  # ground, canopy, far
    gated = range_gate(pts, p.max_range)
    stats, _ = points_to_stats(gated, p)
    assert stats[..., 0].sum() == 1


def test_builder_fuses_frames_in_the_last_frame():
    p = LocalMapParams(resolution=0.5, cells=16, travel=1.0, max_range=10)
    b = LocalMapBuilder(p)
    point = np.array([[2.0, 0.0, 0.3]])
    assert b.add(np.array([0.0, 0.0, 0.0]), point) is None
    stats = b.add(np.array([1.0, 0.0, 0.0]), point)
    assert stats is not None
    # the first frame's point lies 1 m behind in the emitting frame: x = 1.0 -> cell 10
    assert stats[8 + 2, 8, 0] == 1 and stats[8 + 4, 8, 0] == 1
