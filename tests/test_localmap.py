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


def _world_binning(world: np.ndarray, origin: np.ndarray, res: float) -> dict:
    """(i, j) -> (n, sum z, sum z^2) of world points [N, 3] binned straight on the map lattice."""
    out: dict = {}
    for x, y, z in world:
        ij = (int(np.floor((x - origin[0]) / res)), int(np.floor((y - origin[1]) / res)))
        out[ij] = out.get(ij, np.zeros(3)) + [1.0, z, z * z]
    return out


def test_map_lattice_places_cells_one_for_one_on_the_map():
    """[localmap] lattice = "map": a local map built at a pose turned 37 degrees and placed at
    that pose by the filter (its lattice heading added) holds in each map cell exactly the
    points whose world position lies in it, as binning the world points straight on the map's
    lattice does (the robot stands on a map cell's corner). On the robot's lattice most map
    cells end up with other points than theirs."""
    import jax.numpy as jnp

    from gslam_jax import rbpf
    from gslam_jax.rbpf.placement import observation_cells

    res, L = 0.25, 32
    origin = np.array([-10.0, -10.0])
    pose = np.array([origin[0] + 37 * res, origin[1] + 41 * res, np.radians(37.0)])
    rng = np.random.default_rng(3)
    world = np.column_stack([pose[0] + rng.uniform(-2.5, 2.5, 4000),
                             pose[1] + rng.uniform(-2.5, 2.5, 4000), rng.normal(0, 0.3, 4000)])
    c, s = np.cos(pose[2]), np.sin(pose[2])
    d = world[:, :2] - pose[:2]
    robot = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], world[:, 2]])
    expected = _world_binning(world, origin, res)
    cfg = rbpf.FilterConfig(1, (96, 96), tuple(origin), res, L)
    for lattice in ("map", "robot"):
        b = LocalMapBuilder(LocalMapParams(resolution=res, cells=L, max_range=10.0, travel=1.0,
                                           lattice=lattice))
        b.add(pose, robot)
        stats = b.flush()
        heading = b.lattice_headings[-1]
        assert heading == (-pose[2] if lattice == "map" else 0.0)
        assert stats[..., 0].sum() == len(world)
        flat, on_map = observation_cells(jnp.asarray(pose, jnp.float32),
                                         jnp.arange(L * L, dtype=jnp.int32), cfg, heading)
        assert bool(np.all(on_map))
        placed: dict = {}
        for f, st in zip(np.asarray(flat), stats.reshape(-1, 3)):
            if st[0] > 0:
                ij = divmod(int(f), 96)
                placed[ij] = placed.get(ij, np.zeros(3)) + st
        if lattice == "map":
            assert placed.keys() == expected.keys()
            for ij, st in expected.items():
                np.testing.assert_allclose(placed[ij], st, rtol=1e-9, atol=1e-9)
        else:  # a turned lattice placed by its cells' centres: most map cells hold other points
            same = sum(ij in placed and np.allclose(placed[ij], st) for ij, st in expected.items())
            assert same < len(expected) // 2


def test_lattice_heading_wraps_and_names_a_bad_lattice():
    import pytest

    from gslam_jax.vo.localmap import lattice_heading

    assert lattice_heading(1.0, "robot") == 0.0
    assert lattice_heading(1.0, "map") == -1.0
    assert np.isclose(lattice_heading(3 * np.pi / 2, "map"), np.pi / 2)
    with pytest.raises(ValueError, match="lattice 'north' unknown"):
        lattice_heading(0.0, "north")
