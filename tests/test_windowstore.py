"""The window store (``rbpf.windowstore``) against the dense store on small runs: the same
weights, resampling decisions and ancestors, and every particle's whole map the dense one,
on a path that leaves its start and comes back (the cells that re-enter the windows are
refilled from the past local maps)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gslam_jax import rbpf
from gslam_jax.config import ConfigError
from gslam_jax.rbpf import maps, windowstore
from gslam_jax.rbpf.types import Observation

L = 16          # local map side: reach 13 cells
SIDE = 160      # map side, cells of 0.16 m
STEP_CELLS = 8  # [map] tile: cells a particle may move between local maps


def _config(store: str, J: int = 8, history: int = 0, **kw) -> rbpf.FilterConfig:
    return rbpf.FilterConfig(num_particles=J, map_shape=(SIDE, SIDE), map_origin=(0.0, 0.0),
                             resolution=0.16, local_size=L, store=store, tile=STEP_CELLS,
                             pool_tiles=history, **kw)


def _loop_run(rng: np.random.Generator, updates: int = 88):
    """A square loop of side 13 m from (4, 4) m driven twice round (so the second lap revisits
    what the first mapped), a local map every 0.72 m of travel and a frame between; controls in
    the robot frame, local maps of random cells (k in 0..6) observed within 6.5 cells of
    their centre (so the window store's observed reach is shorter than the diagonal)."""
    corners = np.array([[4.0, 4.0], [17.0, 4.0], [17.0, 17.0], [4.0, 17.0]])
    pts = []
    for lap in range(2):
        for c in range(4):
            a, b = corners[c], corners[(c + 1) % 4]
            for s in np.linspace(0.0, 1.0, 18, endpoint=False):
                pts.append(a + s * (b - a))
    pts = np.array(pts[:updates + 1])
    heading = np.arctan2(*np.diff(pts, axis=0)[:, ::-1].T)
    poses = np.column_stack([pts[1:], heading])
    start = np.array([pts[0, 0], pts[0, 1], heading[0]], np.float32)
    prev = np.concatenate([start[None], poses[:-1]])
    controls = []
    for p, q in zip(prev, poses):
        d = q[:2] - p[:2]
        c, s = math.cos(p[2]), math.sin(p[2])
        dtheta = (q[2] - p[2] + np.pi) % (2 * np.pi) - np.pi
        # half the step at each of two frames, the local map at the second
        controls.append([0.5 * (c * d[0] + s * d[1]), 0.5 * (-s * d[0] + c * d[1]), dtheta])
        controls.append([0.5 * (c * d[0] + s * d[1]), 0.5 * (-s * d[0] + c * d[1]), 0.0])
    T = len(controls)
    obs_index = np.where(np.arange(T) % 2 == 1, np.arange(T) // 2, -1).astype(np.int32)
    n = T // 2
    k = rng.integers(0, 7, (n, L, L)).astype(np.float32)
    k[:, :, :3] = 0.0  # some unobserved cells
    centre = np.arange(L) - L // 2 + 0.5
    k[:, np.hypot(centre[:, None], centre[None, :]) > 6.5] = 0.0
    S = k * rng.gamma(2.0, 0.01, k.shape).astype(np.float32)
    return (jnp.asarray(np.array(controls, np.float32)), jnp.asarray(obs_index),
            jnp.asarray(np.stack([k, S], -1)), jnp.asarray(start))


def _filter_runs(**kw) -> dict:
    """store -> (cfg, run_filter's output) of the dense and window stores on ``_loop_run``'s
    run, with ``_config``'s settings plus ``kw``."""
    controls, obs_index, local_obs, start = _loop_run(np.random.default_rng(3))
    out = {}
    for store in ("dense", "window"):
        cfg = maps.resolve_history(_config(store, resample_ratio=0.6, **kw),
                                   int(local_obs.shape[0]), np.asarray(local_obs))
        out[store] = (cfg, jax.jit(rbpf.run_filter, static_argnums=5)(
            jax.random.key(7), rbpf.FilterParams(), controls, obs_index, local_obs, cfg, start))
    return out


def _assert_same_filter(dense, window) -> None:
    """The window store's run has the dense store's resampling decisions (both kinds occur)
    and ancestors, and its log weights and poses to 1e-5, with no map error."""
    assert int(jnp.max(window.infos.map_status)) == 0
    resampled = np.asarray(dense.infos.resampled)
    assert 0 < resampled.sum() < resampled.size  # both decisions occur
    np.testing.assert_array_equal(np.asarray(window.infos.resampled), resampled)
    np.testing.assert_array_equal(np.asarray(window.infos.ancestors),
                                  np.asarray(dense.infos.ancestors))
    np.testing.assert_allclose(np.asarray(window.infos.log_w), np.asarray(dense.infos.log_w),
                               rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(np.asarray(window.infos.pose), np.asarray(dense.infos.pose),
                               rtol=0, atol=1e-5)


@pytest.fixture(scope="module")
def runs():
    return _filter_runs()


def test_the_window_is_sized_by_the_observed_reach(runs):
    """The observed cells lie within 6.5 cells of the local map's centre: the window's reach
    is 7 + 1 cells, not the 16-cell local map's diagonal (12 + 1)."""
    cfg, _ = runs["window"]
    assert (cfg.observed_reach, cfg.reach) == (8, 13)
    assert windowstore.side(cfg) == 48  # 2 (8 + 8) + 2 x 8, a multiple of 8
    assert runs["dense"][0].observed_reach == 0  # other stores keep the whole local map's


def test_observed_reach_of_single_cells():
    """One observed cell: its centre's distance from the local map's centre, rounded up,
    plus one (worked by hand)."""
    one = np.zeros((1, L, L, 2), np.float32)
    corner = one.copy()
    corner[0, 0, 0, 0] = 1.0  # centre (-7.5, -7.5): 10.61 cells
    assert windowstore.observed_reach(corner) == 12
    middle = one.copy()
    middle[0, 8, 8, 0] = 3.0  # centre (0.5, 0.5): 0.71 cells
    assert windowstore.observed_reach(middle) == 2
    assert windowstore.observed_reach(one) == 0


def test_the_path_leaves_the_window_and_comes_back(runs):
    """The test's run is one that needs refills: a particle moves further from its first
    pose than the window's half side, and comes back within a footprint's reach of it."""
    cfg, out = runs["window"]
    C = windowstore.side(cfg)
    xy = np.asarray(out.infos.pose)[:, 0, :2] / cfg.resolution
    far = np.max(np.abs(xy - xy[0]), axis=1)
    assert far.max() > C
    late = far[len(far) // 2:]
    assert late.min() < cfg.reach


def test_weights_resampling_and_ancestors_match_the_dense_store(runs):
    _assert_same_filter(runs["dense"][1], runs["window"][1])


def test_the_informed_proposal_matches_the_dense_store():
    """The informed proposal reads each particle's map at its candidate poses, around the
    pose the window was placed for: the same poses, weights, resampling decisions and
    ancestors as the dense store's on the test's run."""
    out = _filter_runs(proposal="informed")
    _assert_same_filter(out["dense"][1], out["window"][1])


def test_every_particle_map_is_the_dense_one(runs):
    """The whole maps replayed from the paths (``to_dense``) and the windows' cells against the
    dense maps: equal (the same additions in the same order)."""
    _, dense = runs["dense"]
    cfg, window = runs["window"]
    dk, dS = np.asarray(dense.final_state.maps.k), np.asarray(dense.final_state.maps.S)
    wk, wS, _ = (np.asarray(x) for x in maps.to_dense(window.final_state.maps, cfg))
    assert dk.sum() > 0
    np.testing.assert_allclose(wk, dk, rtol=1e-6, atol=0)
    np.testing.assert_allclose(wS, dS, rtol=1e-6, atol=1e-9)
    # the windows hold the dense map's values at every cell they cover
    store = window.final_state.maps
    C = windowstore.side(cfg)
    for j in range(cfg.num_particles):
        oi, oj = (int(x) for x in store.origin[j])
        gi, gj = np.meshgrid(np.arange(oi, oi + C), np.arange(oj, oj + C), indexing="ij")
        ok = (gi >= 0) & (gi < SIDE) & (gj >= 0) & (gj < SIDE)
        cached = np.asarray(store.k[j])[gi % C, gj % C]
        np.testing.assert_array_equal(cached[ok], dk[j][gi[ok], gj[ok]])


def test_window_store_refuses_eq31_a_prior_and_an_unsized_history():
    with pytest.raises(ConfigError, match="unknown_cells"):
        maps.init(_config("window", history=4, unknown_cells="sample"))
    with pytest.raises(ConfigError, match="prior"):
        z = jnp.zeros((SIDE, SIDE), jnp.float32)
        maps.init(_config("window", history=4), (z, z))
    with pytest.raises(ConfigError, match="history"):
        maps.init(_config("window"))


def test_memory_is_known_before_the_run_and_refused_with_the_figure():
    cfg = maps.resolve_history(_config("window", J=1000), 500)
    assert cfg.pool_tiles == 500
    C = windowstore.side(cfg)
    need = maps.map_bytes(cfg)
    assert need == 1000 * (C * C * 8 + 8 + 500 * 12) + 500 * (L * L * 12 + 4 + windowstore.groups(L * L) * 16) + 8
    maps.check_memory(cfg, need)
    with pytest.raises(ConfigError, match=f"{need / 2**30:.2f} GiB"):
        maps.check_memory(cfg, need - 1)
    # independent of the map's area (the dense store's grows with it)
    big = maps.resolve_history(_config("window", J=1000)._replace(map_shape=(8000, 8000)), 500)
    assert maps.map_bytes(big) == need


def test_a_particle_that_outruns_its_window_is_reported():
    """A jump of more than the window allows between two local maps: the write outside the
    window sets MISSED and the host error names [map] tile."""
    cfg = maps.resolve_history(_config("window", J=2), 4)
    state = rbpf.init(cfg, jnp.asarray([5.0, 5.0, 0.0]))
    obs = jnp.ones((L, L, 2), jnp.float32)
    noise = rbpf.update_noise(jax.random.key(0), cfg)
    # one compiled update serves both calls
    update = jax.jit(lambda s: rbpf.update(s, obs, noise.unknown_u, rbpf.FilterParams(), cfg)[0])
    state = update(state)
    state = update(state._replace(pose=state.pose + jnp.asarray([10.0, 0.0, 0.0])))
    bits = int(maps.status(state.maps))
    assert bits & windowstore.MISSED
    with pytest.raises(maps.WindowStoreError, match="tile"):
        maps.check_status(bits, cfg)



def test_a_refill_replays_what_a_search_of_every_past_map_replays(monkeypatch):
    """``_refill`` with its heading-free pre-test of the past local maps (``_near``) against
    the same refill with every recorded map put through the groups' boxes: the same cells
    refilled with the same sums, bit for bit, with R large enough for the pre-test's maps and
    with R below them (the refill then searches every map itself)."""
    rng = np.random.default_rng(5)
    P, U, M = 12, 60, 64
    cfg = _config("window", J=P, history=U, observed_cells=M)
    C = windowstore.side(cfg)
    # local maps of M of their outer cells observed, seen from poses scattered about the
    # map's middle (ground mapped over and over)
    a, b = np.meshgrid(np.arange(L), np.arange(L), indexing="ij")
    centre = np.hypot(a - L // 2 + 0.5, b - L // 2 + 0.5)
    cells_in = np.flatnonzero(centre.ravel() > 7.0)  # the outer 100 cells, 7-10.6 out
    path = rng.normal(0.0, [3.0, 3.0, 2.0], (U, P, 3)).astype(np.float32)
    path[..., :2] += 0.5 * SIDE * cfg.resolution
    store = windowstore.init(cfg)
    record = jax.jit(windowstore._record, static_argnums=3)
    for u in range(U - 7):
        index = np.sort(rng.choice(cells_in, M, replace=False)).astype(np.int32)
        k = rng.integers(0, 4, M).astype(np.float32)
        obs = Observation(jnp.asarray(index), jnp.asarray(k), jnp.asarray(0.1 * k),
                          jnp.int32(0), jnp.float32(rng.uniform(-0.5, 0.5)))
        store = record(store, jnp.asarray(path[u]), obs, cfg)
    # windows about the map's middle, each moved by up to 20 cells an axis
    origin = np.full((P, 2), SIDE // 2 - C // 2, np.int32)
    new = origin + rng.integers(-20, 21, (P, 2)).astype(np.int32)
    lo, hi = np.where(new > origin, origin + C, new), np.where(new > origin, new + C, origin)
    ids = jnp.asarray(np.where(np.arange(P) < P - 1, np.arange(P), P), jnp.int32)  # a pad
    mv = windowstore._Move(jnp.asarray(new), jnp.asarray(np.stack([lo[:, 0], hi[:, 0]], 1)),
                           jnp.asarray(np.stack([lo[:, 1], hi[:, 1]], 1)))
    store = store._replace(origin=jnp.asarray(new))
    zero = jnp.zeros((P, C, C), jnp.float32)

    def refill(R):  # a new function each time: traced with the ``_near`` of the moment
        return jax.jit(lambda *a: windowstore._refill(*a, cfg, R))(store, zero, zero, ids, mv)

    near = jax.vmap(lambda p, m: windowstore._near(p, jnp.arange(U) < store.count, m, C, cfg))(
        store.path, mv)
    most = int(jnp.max(jnp.sum(near, axis=1)))
    assert 4 < most < U
    pre = [refill(R) for R in (U, 4)]
    monkeypatch.setattr(windowstore, "_near", lambda path, recorded, mv, C, cfg: recorded)
    every = [refill(R) for R in (U, 4)]
    for got, want in zip(pre, every):
        assert float(jnp.sum(want[0] > 0)) > 100  # cells were refilled
        np.testing.assert_array_equal(np.asarray(got[0]), np.asarray(want[0]))
        np.testing.assert_array_equal(np.asarray(got[1]), np.asarray(want[1]))
        assert bool(got[2]) == bool(want[2])
