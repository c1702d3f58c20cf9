"""A map small enough that the exhaustive search runs at A's own lattice (no coarse level) is
still refined there and aligned (it once failed with an unbound score)."""

from __future__ import annotations

import numpy as np

from gslam_jax.gridmap.align import AlignParams, align_maps
from test_align_jackknife import _strip


def test_a_small_map_searched_at_the_finest_level_is_aligned() -> None:
    # A 6 x 6 m and B 11 x 11 cells (121: one bucket of 128 padded cells, where 12 x 12 took
    # two), so that the exhaustive search at A's lattice costs a quarter of what 8 x 8 m and
    # 12 x 12 cells did; still at level 1 (asserted) and over the same rocks
    a = _strip(np.zeros(3), (3.0, 3.0), noise=1)
    truth = np.array([-1.2, 0.7, 0.4])  # over three rocks
    b = _strip(truth, (0.9, 0.9), noise=2)  # 11 x 11 cells
    al = align_maps(a, b, AlignParams(mutual=False, jackknife=False), refuse=False)
    assert al.coarse == 1
    np.testing.assert_allclose(al.pose[:2], truth[:2], atol=0.16)
    # a cell's turn at the patch's corner (1.4 m out): the heading's resolution here
    assert abs(al.pose[2] - truth[2]) < np.arctan(0.16 / 1.4)
