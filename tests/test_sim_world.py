"""Worlds: reproducible from the seed, of the right kind, with structure to localise against."""

from __future__ import annotations

import numpy as np
import pytest

from gslam_jax.sim import Material, make_course, make_world, world_for_course


@pytest.mark.parametrize("name", ["mars-yard-a", "arroyo-a", "maze"])
def test_world_is_reproducible_from_its_seed(name: str) -> None:
    course = make_course(name, seed=5)
    a = world_for_course(course, seed=5)
    b = world_for_course(make_course(name, seed=5), seed=5)
    c = world_for_course(course, seed=6)
    assert a.fingerprint() == b.fingerprint()
    np.testing.assert_array_equal(a.height, b.height)
    assert a.fingerprint() != c.fingerprint()


def test_world_kinds_have_their_features() -> None:
    mats = {}
    for name in ("mars-yard-b", "arroyo-b", "maze"):
        w = world_for_course(make_course(name, 0), 0)
        mats[w.kind] = (w, np.bincount(w.material.ravel(), minlength=len(Material)))
    w, m = mats["mars-yard"]
    assert all(m[int(k)] > 0 for k in (Material.ROCK, Material.POLE, Material.BIN,
                                       Material.BUILDING))
    assert m[int(Material.SAND)] > 0.8 * w.material.size  # mostly open sand
    assert (w.rough[w.material == Material.SAND] < 0.02).all()
    assert not w.has_canopy
    w, m = mats["arroyo"]
    assert all(m[int(k)] > 0 for k in (Material.GRASS, Material.BUSH, Material.TREE))
    assert w.has_canopy and np.nanmin(w.canopy_lo - w.ground) > 2.0  # above the overhang band
    w, m = mats["maze"]
    assert m[int(Material.SCRUB)] > 0.5 * w.material.size
    scrub = (w.height - w.ground)[w.material == Material.SCRUB]
    assert np.median(scrub) > 0.8


def test_unknown_world_kind_is_named() -> None:
    with pytest.raises(ValueError, match="desert.*mars-yard"):
        make_world("desert", 0, make_course("maze", 0))
