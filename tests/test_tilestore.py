"""Shared-tile map store against a brute-force NumPy model of dense per-particle maps."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gslam_jax.rbpf import tilebytes, tilesample
from gslam_jax.rbpf import tilestore as ts

H, W, T = 40, 56, 16          # the map is not a whole number of tiles: pages stick out
REACH = 9                     # written cells lie within REACH cells of a centre
WINDOW = ts.window_tiles(REACH, T)


def np_bits(k: np.ndarray) -> np.ndarray:
    """[J, H, W] -> [J, H/8, W/8, 2] uint32 known-cell bits, bit r * 8 + c of each 8 x 8 block."""
    J, h, w = k.shape
    out = np.zeros((J, h // 8, w // 8, 2), np.uint64)
    for r in range(8):
        for c in range(8):
            p = r * 8 + c
            known = (k[:, r::8, c::8] > 0).astype(np.uint64)
            out[..., p // 32] |= known << np.uint64(p % 32)
    return out.astype(np.uint32)


def footprints(rng, n: int, M: int):
    """Flat cells [n, M] within REACH of random centres (some off the map), values with zeros."""
    ci = rng.integers(-3, H + 3, n)
    cj = rng.integers(-3, W + 3, n)
    gi = ci[:, None] + rng.integers(-REACH, REACH + 1, (n, M))
    gj = cj[:, None] + rng.integers(-REACH, REACH + 1, (n, M))
    on_map = (gi >= 0) & (gi < H) & (gj >= 0) & (gj < W)
    cells = np.where(on_map, gi * W + gj, H * W)
    k = np.where(rng.random(M) < 0.2, 0.0, rng.integers(1, 5, M)).astype(np.float32)
    S = np.where(k > 0, rng.random(M), 0.0).astype(np.float32)
    return cells.astype(np.int32), on_map, k, S


def np_add(kmap, smap, parts, cells, on_map, k, S):
    for i, j in enumerate(parts):
        for m in range(cells.shape[1]):  # in order, as the scatter
            if on_map[i, m]:
                kmap[j].reshape(-1)[cells[i, m]] += k[m]
                smap[j].reshape(-1)[cells[i, m]] += S[m]


def np_ranked_cells(k: np.ndarray) -> np.ndarray:
    """Flat cells of a map's known cells (k [H, W] > 0) in eq. 31's rank order: rows of 8 x 8
    blocks, blocks left to right, then the cells of a block row by row (brute force)."""
    h, w = k.shape
    return np.array([(8 * bi + r) * w + 8 * bj + c
                     for bi in range(h // 8) for bj in range(w // 8)
                     for r in range(8) for c in range(8) if k[8 * bi + r, 8 * bj + c] > 0],
                    np.int64)


def check_sampler(store: ts.TileStore, kmap: np.ndarray, rng) -> None:
    """``tilesample.sample_known`` draws, for every particle and uniform, the cell of rank
    floor(u * #known) in the brute-force order (the dense store's sampler's)."""
    J = kmap.shape[0]
    u = rng.random((J, 50)).astype(np.float32)
    u[:, :2] = [0.0, np.nextafter(np.float32(1), np.float32(0))]  # the first and last ranks
    idx, total = sample(store, jnp.arange(J), jnp.asarray(u), (H, W))
    for j in range(J):
        order = np_ranked_cells(kmap[j])
        assert int(total[j]) == len(order)
        if len(order):
            r = np.clip(np.floor(u[j] * np.float32(len(order))).astype(np.int64), 0,
                        len(order) - 1)
            np.testing.assert_array_equal(np.asarray(idx[j]), order[r])


write = jax.jit(ts.write, static_argnames=("width", "window"))
sample = jax.jit(tilesample.sample_known, static_argnames="map_shape")
resample = jax.jit(ts.resample)
to_dense = jax.jit(ts.to_dense, static_argnames="map_shape")
read = jax.jit(ts.read, static_argnames="width")


def check_invariants(store: ts.TileStore) -> None:
    P = store.refcount.shape[0]
    page = np.asarray(store.page)
    counts = np.bincount(page.reshape(-1), minlength=P + 1)[:P]
    np.testing.assert_array_equal(np.asarray(store.refcount), counts)
    n_free = int(store.n_free)
    free = np.asarray(store.free)[:n_free]
    assert sorted(free.tolist()) == np.flatnonzero(counts == 0).tolist()
    for j in range(page.shape[0]):  # a particle never holds one tile in two pages
        held = page[j][page[j] < P]
        assert len(np.unique(held)) == len(held)
    assert not np.asarray(store.kpool[P]).any() and not np.asarray(store.spool[P]).any()


@pytest.mark.slow
@pytest.mark.parametrize("bits", [False, True])
def test_writes_and_resampling_match_dense_model(bits):
    rng = np.random.default_rng(0)
    J, M, block, P = 7, 60, 3, 300
    store = ts.init(J, (H, W), T, P, bits)
    kmap = np.zeros((J, H, W), np.float32)
    smap = np.zeros((J, H, W), np.float32)
    if bits:
        check_sampler(store, kmap, rng)  # no known cell anywhere: totals 0
    for it in range(12):
        for j0 in range(0, J, block):
            parts = np.arange(j0, min(j0 + block, J), dtype=np.int32)
            cells, on_map, k, S = footprints(rng, len(parts), M)
            # reads before the write see the model's maps
            kr, sr = read(store, jnp.asarray(parts), jnp.asarray(cells), jnp.asarray(on_map), W)
            want_k = np.where(on_map, kmap[parts].reshape(len(parts), -1)[
                np.arange(len(parts))[:, None], np.minimum(cells, H * W - 1)], 0)
            np.testing.assert_array_equal(np.asarray(kr), want_k)
            store = write(store, jnp.asarray(parts), jnp.asarray(cells), jnp.asarray(on_map),
                          jnp.asarray(k), jnp.asarray(S), width=W, window=WINDOW)
            np_add(kmap, smap, parts, cells, on_map, k, S)
        if it % 3 == 1:  # resampling: some particles die, others get several children
            anc = np.sort(rng.choice(J, J, p=rng.dirichlet(np.ones(J) * 0.5))).astype(np.int32)
            store = resample(store, jnp.asarray(anc))
            kmap, smap = kmap[anc], smap[anc]
        assert int(store.status) == 0
        check_invariants(store)
        k_d, s_d, b_d = to_dense(store, (H, W))
        np.testing.assert_array_equal(np.asarray(k_d), kmap)
        np.testing.assert_array_equal(np.asarray(s_d), smap)
        if bits:
            np.testing.assert_array_equal(np.asarray(b_d), np_bits(kmap))
            np.testing.assert_array_equal(
                np.asarray(ts.known_bits(store, jnp.arange(2, 5), (H, W))), np_bits(kmap)[2:5])
            check_sampler(store, kmap, rng)
    # sharing happened: fewer live tiles than pages written
    assert int(ts.live_tiles(store)) < int(np.sum(np.asarray(store.page) < P))


@pytest.mark.slow
def test_a_grown_pool_holds_the_same_maps_and_goes_on_like_the_dense_model():
    """``grow`` mid-run, with some tiles shared and some freed: the maps read the same, the
    bookkeeping holds, and writes and resamplings after it match the NumPy model. (The shapes
    after growing are the previous test's, so its compilations are reused.)"""
    rng = np.random.default_rng(1)
    J, M, block = 7, 60, 3
    store = ts.init(J, (H, W), T, 40, True)
    kmap = np.zeros((J, H, W), np.float32)
    smap = np.zeros((J, H, W), np.float32)
    for it in range(8):
        if it == 2:
            assert int(store.status) == 0
            before = [np.asarray(x) for x in to_dense(store, (H, W))]
            free = int(store.n_free)
            assert 0 < free < 40  # some tiles taken, some free
            store = ts.grow(store, 300)
            check_invariants(store)
            assert int(store.n_free) == free + 260
            for a, b in zip(before, to_dense(store, (H, W))):
                np.testing.assert_array_equal(np.asarray(b), a)
        for j0 in range(0, J, block):
            parts = np.arange(j0, min(j0 + block, J), dtype=np.int32)
            cells, on_map, k, S = footprints(rng, len(parts), M)
            store = write(store, jnp.asarray(parts), jnp.asarray(cells), jnp.asarray(on_map),
                          jnp.asarray(k), jnp.asarray(S), width=W, window=WINDOW)
            np_add(kmap, smap, parts, cells, on_map, k, S)
        if it % 3 == 1:
            anc = np.sort(rng.choice(J, J, p=rng.dirichlet(np.ones(J) * 0.5))).astype(np.int32)
            store = resample(store, jnp.asarray(anc))
            kmap, smap = kmap[anc], smap[anc]
    assert int(store.status) == 0
    check_invariants(store)
    assert int(store.peak) > 40  # the grown tiles were used
    k_d, s_d, b_d = to_dense(store, (H, W))
    np.testing.assert_array_equal(np.asarray(k_d), kmap)
    np.testing.assert_array_equal(np.asarray(s_d), smap)
    np.testing.assert_array_equal(np.asarray(b_d), np_bits(kmap))
    check_sampler(store, kmap, rng)
    with pytest.raises(ValueError, match="cannot shrink"):
        ts.grow(store, 299)


def _write_one(store: ts.TileStore, j: int, cell: int, v: float) -> ts.TileStore:
    """Add (k, S) = (v, v) to one cell of particle j's map."""
    return write(store, jnp.array([j], jnp.int32), jnp.array([[cell]], jnp.int32),
                 jnp.array([[True]]), jnp.array([v], jnp.float32), jnp.array([v], jnp.float32),
                 width=W, window=WINDOW)


def test_copy_on_write_leaves_siblings_untouched_and_frees_dead_tiles():
    store = ts.init(3, (H, W), T, 20, False)
    store = _write_one(store, 0, 5, 1.0)
    assert int(ts.live_tiles(store)) == 1
    store = resample(store, jnp.array([0, 0, 0], jnp.int32))  # one tile, three holders
    assert int(ts.live_tiles(store)) == 1 and int(store.refcount.max()) == 3
    store = _write_one(store, 1, 5, 2.0)                      # copy-on-write
    k, _, _ = to_dense(store, (H, W))
    assert np.asarray(k[:, 0, 5]).tolist() == [1.0, 3.0, 1.0]
    assert int(ts.live_tiles(store)) == 2
    store = resample(store, jnp.array([1, 1, 1], jnp.int32))  # the original tile has no holder
    assert int(ts.live_tiles(store)) == 1
    check_invariants(store)


def test_every_holder_writing_in_one_block_keeps_one_tile():
    """Two holders of one tile write it in one block: one copy is made, not two. (The store
    has the previous test's shape, so its compiled single-particle write is reused; the third
    particle holds nothing.)"""
    store = ts.init(3, (H, W), T, 20, False)
    store = _write_one(store, 0, 7, 1.0)
    store = resample(store, jnp.array([0, 0, 1], jnp.int32))  # particles 0 and 1 hold it
    assert int(ts.live_tiles(store)) == 1 and int(store.refcount.max()) == 2
    ones = jnp.ones((1,), jnp.float32)
    store = write(store, jnp.array([0, 1], jnp.int32), jnp.array([[7], [7]], jnp.int32),
                  jnp.ones((2, 1), bool), ones, ones, width=W, window=WINDOW)
    assert int(ts.live_tiles(store)) == 2  # one copy, not two
    k, _, _ = to_dense(store, (H, W))
    assert np.asarray(k[:, 0, 7]).tolist() == [2.0, 2.0, 0.0]
    assert int(store.status) == 0
    check_invariants(store)


def test_pool_exhaustion_is_flagged_and_changes_nothing():
    rng = np.random.default_rng(3)
    J, P = 4, 5
    store = ts.init(J, (H, W), T, P, True)
    parts = jnp.arange(J, dtype=jnp.int32)
    cells, on_map, k, S = footprints(rng, J, 200)  # needs more than 5 tiles
    before = to_dense(store, (H, W))
    store = write(store, parts, jnp.asarray(cells), jnp.asarray(on_map), jnp.asarray(k),
                  jnp.asarray(S), width=W, window=WINDOW)
    assert int(store.status) & ts.POOL_EXHAUSTED
    for a, b in zip(before, to_dense(store, (H, W))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert int(store.n_free) == P
    with pytest.raises(tilebytes.PoolExhaustedError, match=r"\[map\] pool_tiles = 5"):
        tilebytes.check_status(store.status, P)


@pytest.mark.slow
def test_store_vmaps_over_independent_filters():
    """Two filters' stores stacked and written in one vmapped call agree with two calls.
    (Shapes as in test_writes_and_resampling_match_dense_model[True]: its compiled write of
    a block of 3 particles serves the two single calls.)"""
    rng = np.random.default_rng(4)
    parts = jnp.arange(3, dtype=jnp.int32)
    fp = [footprints(rng, 3, 60) for _ in range(2)]
    stores = [ts.init(7, (H, W), T, 300, True) for _ in range(2)]
    args = [[jnp.asarray(x) for x in f] for f in fp]
    one = [write(s, parts, *a, width=W, window=WINDOW) for s, a in zip(stores, args)]
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *stores)
    both = jax.jit(jax.vmap(lambda s, c, o, k, S: ts.write(s, parts, c, o, k, S, W, WINDOW)))(
        stacked, *[jnp.stack(x) for x in zip(*args)])
    for i in range(2):
        assert int(ts.live_tiles(one[i])) > 0
        for a, b in zip(to_dense(one[i], (H, W)),
                        to_dense(jax.tree.map(lambda x: x[i], both), (H, W))):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["ignore", "sample"])
def test_filter_on_shared_store_equals_dense(mode):
    """The whole filter on the shared store (small tiles, blocks of 3 and a tail, resampling
    events) gives the dense store's maps bit for bit, its known-cell bits, resampling choices
    and log weights (within 1e-5), on the same draws."""
    from cached_runs import shared_run

    from gslam_jax import rbpf as gf
    from gslam_jax.driver import observations, sizing

    run = shared_run(30, seed=2)  # both modes share the course
    obs = jnp.asarray(observations.local_observations(run, 1e-6))
    base = gf.FilterConfig(11, (160, 160), (-8.0, -12.8), 0.16, obs.shape[1], unknown_cells=mode,
                           unknown_samples=64, observed_cells=sizing.observed_cells(run),
                           particle_block=3, resample_ratio=0.8)
    args = (jnp.asarray(run.controls, jnp.float32), jnp.asarray(run.obs_index), obs)
    dense = gf.run_filter(jax.random.key(4), gf.FilterParams(), *args, base)
    shared_cfg = base._replace(store="shared", tile=16)
    shared = gf.run_filter(jax.random.key(4), gf.FilterParams(), *args, shared_cfg)
    assert int(np.sum(dense.infos.resampled)) >= 2
    np.testing.assert_array_equal(shared.infos.resampled, dense.infos.resampled)
    np.testing.assert_array_equal(shared.infos.ancestors, dense.infos.ancestors)
    np.testing.assert_allclose(shared.infos.log_w, dense.infos.log_w, atol=1e-5)
    np.testing.assert_array_equal(shared.infos.pose, dense.infos.pose)
    assert not np.any(shared.infos.map_status)
    tiles = shared.final_state.maps
    k, S, bits = to_dense(tiles, base.map_shape)
    np.testing.assert_array_equal(k, dense.final_state.maps.k)
    np.testing.assert_array_equal(S, dense.final_state.maps.S)
    np.testing.assert_array_equal(bits, dense.final_state.maps.known_bits)
    k5, S5 = gf.particle_map(shared.final_state, 5, shared_cfg)
    np.testing.assert_array_equal(k5, dense.final_state.maps.k[5])
    np.testing.assert_array_equal(S5, dense.final_state.maps.S[5])
    # the pool holds less than every particle's map
    assert int(tiles.peak) < 11 * int(np.prod(tiles.page.shape[1:]))


def _pool_run_and_config():
    """A 12-frame course and a config whose 30-tile pool (5 particles, eq. 30) runs out on
    it."""
    import dataclasses

    from cached_runs import shared_run

    from gslam_jax.config import Config

    c = Config()
    config = dataclasses.replace(
        c, filter=dataclasses.replace(c.filter, particles=5, unknown_cells="ignore"),
        map=dataclasses.replace(c.map, store="shared", tile=16, pool_tiles=30))
    return shared_run(12, seed=2), config


def test_filter_reports_pool_exhaustion_per_frame():
    """The scan reports the status per frame. Fed as ``slam.run_slam`` feeds it (one chunk),
    so the next test reuses this compilation."""
    from gslam_jax import rbpf as gf
    from gslam_jax.driver import observations, sizing

    run, config = _pool_run_and_config()
    cfg = sizing.filter_config(config, run)
    assert cfg.store == "shared" and cfg.pool_tiles == 30
    state = gf.init(cfg, jnp.asarray(run.start_pose(), jnp.float32))
    keys = gf.frame_keys(jax.random.key(config.filter.seed), run.num_frames)
    _, (infos, _, _) = gf.scan_frames(
        state, keys, jnp.asarray(np.asarray(run.controls, np.float32)),
        jnp.asarray(np.asarray(run.obs_index, np.int32)),
        observations.map_observations(run, config), sizing.filter_params(config), cfg,
        jnp.asarray(run.lattice_heading_array()), None)
    status = np.asarray(infos.map_status)
    assert status[-1] & ts.POOL_EXHAUSTED
    assert np.all(np.diff(status) >= 0)  # sticky: the frame it first happened stays findable


def test_run_slam_names_the_setting_and_frame_when_the_pool_runs_out():
    from gslam_jax.driver import slam

    run, config = _pool_run_and_config()
    exhausted = r"^frame \d+: .*\[map\] pool_tiles = 30"
    with pytest.raises(tilebytes.PoolExhaustedError, match=exhausted):
        slam.run_slam(run, config)


# An automatic pool capped at 120 tiles: the 12-frame course's first frames fit, frame 5 (an
# update and a resampling) does not, and 240 tiles hold the whole run (one regrow).
AUTOMATIC_START = 120


def _automatic(config, monkeypatch, start: int = AUTOMATIC_START):
    """``config`` with an automatic pool (``[map] pool_tiles = 0``) that starts at ``start``
    tiles."""
    import dataclasses

    from gslam_jax.rbpf import maps

    real = maps.pool_tiles
    monkeypatch.setattr(maps, "pool_tiles", lambda cfg: cfg.pool_tiles or min(real(cfg), start))
    return dataclasses.replace(config, map=dataclasses.replace(config.map, pool_tiles=0))


@pytest.fixture(scope="module")
def dense_pool_run():
    """The pool tests' course on the dense store, one chunk: the reference for the runs on a
    grown shared pool (results do not depend on the chunk: test_filter.py checks it)."""
    import dataclasses

    from gslam_jax.driver import slam

    run, config = _pool_run_and_config()
    return slam.run_slam(run, dataclasses.replace(
        config, map=dataclasses.replace(config.map, store="dense")), chunk=run.num_frames)


def test_a_chunk_that_exhausts_an_automatic_pool_runs_again_in_a_grown_one(monkeypatch,
                                                                            dense_pool_run):
    """The whole run as one chunk, an automatic pool of 120 tiles: the chunk runs out, is run
    again from its start with the pool grown (to 240 tiles, which hold the run), says so, and
    the run is the dense store's bit for bit."""
    from gslam_jax.driver import slam
    from gslam_jax.rbpf import maps

    run, config = _pool_run_and_config()
    automatic = _automatic(config, monkeypatch)
    with pytest.warns(maps.MapStoreNotice, match=r"^frame \d+: .*pool ran out; frames from 0 "
                                                 r"run again after it grew from 120 to 240 tiles"):
        shared = slam.run_slam(run, automatic, chunk=run.num_frames)
    dense = dense_pool_run
    np.testing.assert_array_equal(shared.best_path, dense.best_path)
    np.testing.assert_array_equal(shared.kmap, dense.kmap)
    np.testing.assert_array_equal(shared.ess, dense.ess)


def test_an_automatic_pool_without_room_to_grow_says_it_is_automatic(monkeypatch):
    """No memory to grow an automatic pool (120 tiles here) into: the error says the pool was
    automatic and to fix its size, not that a setting of 120 was. (The run compiled as the
    previous test's first try.)"""
    from gslam_jax.driver import sizing, slam
    from gslam_jax.rbpf import maps

    run, config = _pool_run_and_config()
    automatic = _automatic(config, monkeypatch)
    cfg = sizing.filter_config(automatic, run)
    monkeypatch.setattr(slam, "map_memory", lambda: (3 * maps.map_bytes(cfg), "test memory"))
    with pytest.raises(tilebytes.PoolExhaustedError,
                       match=r"^frame \d+: .*automatic pool of 120 tiles ran out, and the memory "
                             r"has no room to grow it.*set \[map\] pool_tiles to a fixed size "
                             r"above 120"):
        slam.run_slam(run, automatic, chunk=run.num_frames)


def test_run_slam_grows_an_automatic_pool_and_gets_the_dense_stores_numbers(monkeypatch,
                                                                             dense_pool_run):
    """An automatic pool of 200 tiles, in two chunks of 6 frames: the first chunk fits, takes
    about 120 tiles at once, and leaves fewer free than twice that plus an update's worth, so
    the pool grows between the chunks (once), says so, and the run is the dense store's bit
    for bit."""
    from gslam_jax.driver import sizing, slam
    from gslam_jax.rbpf import maps

    run, config = _pool_run_and_config()
    automatic = _automatic(config, monkeypatch, start=200)
    with pytest.warns(maps.MapStoreNotice) as notices:
        shared = slam.run_slam(run, automatic, chunk=6)
    said = [str(n.message) for n in notices]
    assert len(said) == 1, said  # one growth, between the chunks (no chunk ran out)
    assert re.match(r"^frame 6: .*pool grew from 200 to \d+ tiles", said[0]), said
    dense = dense_pool_run
    np.testing.assert_array_equal(shared.best_path, dense.best_path)
    np.testing.assert_array_equal(shared.kmap, dense.kmap)
    np.testing.assert_array_equal(shared.smap, dense.smap)
    np.testing.assert_array_equal(shared.ess, dense.ess)
    assert shared.map_bytes > maps.map_bytes(sizing.filter_config(automatic, run))


def test_auto_store_is_dense_when_it_fits_and_shared_with_a_notice_otherwise():
    from gslam_jax import rbpf as gf
    from gslam_jax.rbpf import maps

    cfg = gf.FilterConfig(100, (256, 256), (0.0, 0.0), 0.16, 64, store="auto",
                          unknown_cells="ignore")
    need = maps.map_bytes(cfg._replace(store="dense"))
    assert need == 100 * 256 * 256 * 2 * 4  # k and S, float32
    assert maps.choose_store(cfg, available=need).store == "dense"
    with pytest.warns(maps.MapStoreNotice, match="shared tile store"):
        shared = maps.choose_store(cfg, available=need - 1)
    assert shared.store == "shared"
    assert maps.map_bytes(shared) < need


@pytest.mark.parametrize("mode", ["ignore", "sample"])
def test_map_bytes_are_what_each_store_allocates(mode):
    """The byte accounting the memory check and the results use (``maps.map_bytes``) is the
    size of the arrays ``maps.init`` allocates, for either store (the dense store's two-int
    row range and the tile store's three scalars aside); the dense store's peak is its
    allocation."""
    from gslam_jax import rbpf as gf
    from gslam_jax.rbpf import maps

    cfg = gf.FilterConfig(6, (96, 136), (0.0, 0.0), 0.16, 16, unknown_cells=mode)
    for store, extra in (("dense", 2 * 4), ("shared", 3 * 4)):
        c = cfg._replace(store=store, tile=16)
        allocated = sum(x.nbytes for x in jax.tree.leaves(maps.init(c)))
        assert allocated == maps.map_bytes(c) + extra, store
    dense = cfg._replace(store="dense")
    assert maps.peak_bytes(maps.init(dense), dense) == maps.map_bytes(dense)


def test_search_and_tune_do_not_score_a_run_whose_pool_ran_out():
    """A search scores such a run NaN (never best, with a warning naming the setting); a tuning
    step stops with the store's error."""
    from gslam_jax.tuning import gradient as tuning
    from gslam_jax.tuning import search
    from gslam_jax.tuning.space import SearchError, parse_space

    run, config = _pool_run_and_config()
    space = parse_space({"alpha_d": [0.05, 0.2]})
    with pytest.raises(SearchError, match=r"\[map\] pool_tiles"):
        search.search(run, config, space, design="sobol", n=2)
    exhausted = r"^tune step 0: .*\[map\] pool_tiles = 30"
    with pytest.raises(tilebytes.PoolExhaustedError, match=exhausted):
        tuning.tune(run, config, "supervised", names=["alpha_d"], steps=1, runs_per_step=1)
