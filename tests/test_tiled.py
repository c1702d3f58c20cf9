"""Tiled copy-on-write reference: tile storage, the known-cell order, and equivalence with the
dense filter (same draws -> same weights, poses and maps, in both unknown-cell modes)."""

import contextlib
import io
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import gslam_jax
from gslam_jax.tiled import Ledger, TileMap, tile_cells


def test_tile_size_must_be_whole_cells():
    assert tile_cells(10.0, 0.2) == 50
    assert tile_cells(10.24, 0.16) == 64
    with pytest.raises(ValueError,
                       match=r"10.0 m is 62.5 cells at resolution 0.16 m.*9.92 m \(62 cells\)"):
        tile_cells(10.0, 0.16)


def test_copy_on_write_and_memory_ledger():
    ledger = Ledger()
    a = TileMap(4, ledger)
    k = np.zeros((6, 6), np.float32)
    k[1, 1] = 2.0
    a.add(2, 2, k, k * 0.5)          # touches only tile (0, 0): cell (3, 3)
    assert ledger.live_tiles == 1 and ledger.live_bytes == 2 * 16 * 4
    b = a.share()
    assert a.tiles[(0, 0)] is b.tiles[(0, 0)] and ledger.live_tiles == 1
    b.add(2, 2, k, k)                # first write to a shared tile: private copy
    assert a.tiles[(0, 0)] is not b.tiles[(0, 0)] and ledger.live_tiles == 2
    assert a.read(3, 3, 1, 1)[0][0, 0] == 2.0 and b.read(3, 3, 1, 1)[0][0, 0] == 4.0
    a.release()
    assert ledger.live_tiles == 1 and ledger.peak_bytes == 2 * 2 * 16 * 4


def test_known_cells_follow_block_order():
    """Blocks of 8 x 8 row-major over the map, then row-major inside a block."""
    rng = np.random.default_rng(0)
    H = W = 24
    k = (rng.uniform(size=(H, W)) < 0.3).astype(np.float32)
    m = TileMap(5, Ledger())         # tiles that straddle blocks
    m.add(0, 0, k, k)
    _, kk, _ = m.known_cells(W // 8)
    order = [(i, j) for bi in range(3) for bj in range(3) for i in range(8 * bi, 8 * bi + 8)
             for j in range(8 * bj, 8 * bj + 8) if k[i, j] > 0]
    keys, _, _ = m.known_cells(W // 8)
    assert len(keys) == len(order) and np.all(np.diff(keys) > 0)
    got = [((key // 64) // 3 * 8 + (key % 64) // 8, (key // 64) % 3 * 8 + key % 8) for key in keys]
    assert got == order


def _equivalence() -> dict:
    """Both filters on a loop course (run in a subprocess without FMA contraction)."""
    import jax
    import jax.numpy as jnp

    sys.path.insert(0, str(Path(__file__).parent))
    from synthetic import make_run

    from gslam_jax import rbpf
    from gslam_jax.app.compare import check_agreement
    from gslam_jax.app.dense_timing import DenseOutput
    from gslam_jax.driver.observations import local_observations
    from gslam_jax.driver.sizing import map_extent, observed_cells
    from gslam_jax.tiled.reference import draw_noise, run_tiled
    from gslam_jax.vo.localmap import LocalMapParams

    robot_run, _ = make_run(seed=0, steps=70)
    # the same course with local maps on the map's lattice (``Run.lattice_headings``): the loop
    # turns through every heading, so every lattice angle is placed
    map_run, _ = make_run(seed=0, steps=70, params=LocalMapParams(
        resolution=0.16, max_range=5.0, travel=1.0, lattice="map"))
    out = {}
    # "ignore" in one pass over the particles; "sample" in blocks of 5 (3 blocks and a tail of 1).
    # and "ignore" with adaptive tempering (issue 16), which the reference solves on its own.
    # "sample" also with cross-track motion noise (MotionParams.alpha_cross) and with a frame
    # in five scaled as the fallback odometry's ([motion] fallback_scale).
    for mode, block, temper, lattice in (("ignore", 16, "fixed", "robot"),
                                         ("sample", 5, "fixed", "robot"),
                                         ("ignore", 16, "adaptive", "robot"),
                                         ("sample", 5, "fixed", "map")):
        run = map_run if lattice == "map" else robot_run
        obs = local_observations(run, 1e-4)
        L = obs.shape[1]
        probe = rbpf.FilterConfig(16, (8, 8), (0.0, 0.0), 0.16, L, unknown_cells=mode)
        ext = map_extent(run.vo_poses(), L, 0.16, -2.5, probe.window)  # footprints reach the edge
        cfg = rbpf.FilterConfig(16, ext.shape, ext.origin, 0.16, L, unknown_cells=mode,
                                unknown_samples=64, observed_cells=observed_cells(run),
                                particle_block=block, tempering=temper,
                                ess_target=0.6).validate()
        assert cfg.max_observed < L * L  # the compacted update is what is compared
        key = jax.random.key(3)
        params = rbpf.FilterParams()
        if mode == "sample":
            params = params._replace(motion=params.motion._replace(alpha_cross=0.03))
        headings = run.lattice_heading_array()
        fallback = scale = None  # "sample" on the robot's lattice: every fifth frame the
        if mode == "sample" and lattice == "robot":  # fallback's, its noise 3x the VO's
            fallback = np.arange(run.num_frames) % 5 == 2
            params = params._replace(motion=params.motion._replace(fallback_scale=3.0))
            scale = np.where(fallback, 3.0, 1.0)
        d = rbpf.run_filter(key, params, jnp.asarray(run.controls, jnp.float32),
                            jnp.asarray(run.obs_index), jnp.asarray(obs), cfg,
                            lattice_headings=jnp.asarray(headings),
                            fallback=None if fallback is None else jnp.asarray(fallback))
        i = jax.device_get(d.infos)
        dense = DenseOutput(i.pose, i.log_w, i.ess, i.resampled, np.asarray(d.final_state.maps.k),
                            np.asarray(d.final_state.maps.S), 0, 0.0, 0.0,
                            ancestors=np.asarray(i.ancestors))
        draws = draw_noise(key, run.obs_index, cfg)  # the dense run's, for the reference's runs
        tiled = run_tiled(key, params, run.controls, run.obs_index, obs, cfg, tile_size=16 * 0.16,
                          lattice_headings=headings, noise_scale=scale, draws=draws)
        name = f"{mode}-{temper}" + ("" if lattice == "robot" else f"-{lattice}")
        out[name] = check_agreement(dense, tiled, cfg)
        if temper == "adaptive":  # following the dense decisions: real differences still show
            out["follow"] = _follow_cases(dense, run, obs, cfg, key, params, draws)
        out[name]["off_map_updates"] = int(np.sum(i.extent_violations))
        out[name]["max_shared"] = float(tiled.shared_mean.max())
        out[name]["mem_drops"] = int(np.sum(np.diff(tiled.memory_bytes) < 0))
        out[name]["tempered_updates"] = int(np.sum(np.asarray(i.exponent) < 1.0))
    return out


def _follow_cases(dense, run, obs, cfg, key, params, draws) -> dict:
    """The reference given the dense decisions as they are, and perturbed for real at the
    second resampling: one ancestor moved half the particles along, or the decision flipped
    at an update whose ESS is nowhere near the threshold (``draws``: the run's random numbers,
    ``draw_noise(key, ...)``, made once for the three)."""
    from gslam_jax.app.compare import check_agreement
    from gslam_jax.tiled.reference import Decisions, run_tiled

    res, anc = np.asarray(dense.resampled), np.asarray(dense.ancestors)
    J = anc.shape[1]
    t = int(np.flatnonzero(res)[1])
    moved = anc.copy()
    moved[t, 0] = (moved[t, 0] + J // 2) % J
    far = np.abs(np.asarray(dense.ess) / (cfg.resample_ratio * J) - 1) > 0.05
    flip_at = int(np.flatnonzero(far & (np.asarray(run.obs_index) >= 0))[0])
    flipped = res.copy()
    flipped[flip_at] = not flipped[flip_at]
    flipped_anc = anc.copy()
    flipped_anc[flip_at] = np.arange(J)
    out = {}
    for case, decisions in (("as_is", Decisions(res, anc)), ("ancestor", Decisions(res, moved)),
                            ("decision", Decisions(flipped, flipped_anc))):
        tiled = run_tiled(key, params, run.controls, run.obs_index, obs, cfg, 16 * 0.16,
                          follow=decisions, draws=draws)
        perturbed = dense._replace(resampled=decisions.resampled, ancestors=decisions.ancestors)
        out[case] = check_agreement(dense if case == "as_is" else perturbed, tiled, cfg)
        out[case]["perturbed_at"] = {"as_is": None, "ancestor": t, "decision": flip_at}[case]
    return out


def test_tiled_reference_reproduces_dense_filter():
    # the package this test imports, not whichever one is installed (a worktree beside main)
    root = str(Path(gslam_jax.__file__).parent.parent)
    # No FMA contraction (AVX only). LLVM optimisation level 0: IEEE semantics either way (no
    # fast-math), the same numbers as the default level, in about 60% of the compile time.
    # The suite's own XLA_FLAGS (conftest: the classic emitters) are kept: faster to compile.
    path = os.pathsep.join([root, os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=path,
               XLA_FLAGS=f"{os.environ.get('XLA_FLAGS', '')} --xla_cpu_max_isa=AVX "
                         "--xla_backend_optimization_level=0".strip())
    proc = subprocess.run([sys.executable, __file__], env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    follow = res.pop("follow")
    assert follow["as_is"]["ok"] and follow["as_is"]["rounding_events"] == 0, follow["as_is"]
    for case in ("ancestor", "decision"):  # a real difference is not taken for rounding
        r = follow[case]
        assert not r["ok"] and r["rounding_events"] == 0, (case, r)
        assert r["diverged_at"] == r["perturbed_at"], (case, r)
    assert follow["ancestor"]["ancestor_mismatches"] >= 1
    assert follow["decision"]["resampling_mismatches"] >= 1
    for mode, r in res.items():
        assert r["resampling_events"] >= 3, (mode, r)
        assert r["resampling_mismatches"] == 0, (mode, r)
        assert r["log_w"] <= 1e-4 and r["pose"] <= 1e-5, (mode, r)
        assert r["k"] == 0.0 and r["S_rel"] <= 1e-6, (mode, r)
        assert r["max_shared"] > 0 and r["mem_drops"] > 0, (mode, r)  # copies share tiles
    assert max(r["off_map_updates"] for r in res.values()) > 0  # the off-map rule is exercised
    assert res["ignore-fixed"]["tempered_updates"] == 0
    assert res["ignore-adaptive"]["tempered_updates"] >= 3  # the tempering rule is exercised
    assert "sample-fixed-map" in res  # local maps on the map's lattice, placed by both


def test_dense_update_timing_replays_the_run(compared):
    """`gslam compare` times the dense updates by replaying the run frame by frame: the replay
    must make the same resampling decisions as the scanned run (same draws), one time each.
    (The fixture's ``compare`` kept its dense output: the scanned run's decisions and the
    replay's, from ``time_dense_updates``.)"""
    run, _, _, seen = compared
    dense = seen["dense"]
    seconds, resampled = dense.run_update_seconds, dense.run_resampled
    at_updates = np.asarray(dense.resampled)[np.asarray(run.obs_index) >= 0]
    assert seconds.shape == (run.num_local_maps,) and np.all(seconds > 0)
    assert at_updates.sum() >= 2
    np.testing.assert_array_equal(resampled, at_updates)


def test_ledger_counts_known_cell_caches():
    """In "sample" mode a tile also holds its known cells (int64 keys, float32 k and S): the
    ledger counts them (``cache_bytes``, and in ``live_bytes`` / ``peak_bytes``)."""
    ledger = Ledger()
    a = TileMap(4, ledger)
    k = np.zeros((8, 8), np.float32)
    k[1, 1] = k[5, 6] = 2.0
    a.add(0, 0, k, k)                # tiles (0, 0) and (1, 1), one known cell each
    cells = ledger.live_bytes
    keys, kk, SS = a.known_cells(1)
    cache = keys.nbytes + kk.nbytes + SS.nbytes
    assert cache == 2 * (8 + 4 + 4) and ledger.cache_bytes == cache
    assert ledger.live_bytes == cells + cache
    a.known_cells(1)                 # cached: counted once
    assert ledger.live_bytes == cells + cache
    b = a.share()
    b.add(0, 0, k, k)                # private copies for b, without caches; a's tiles keep theirs
    assert ledger.cache_bytes == cache and ledger.live_bytes == 2 * cells + cache
    a.add(0, 0, k, k)                # a's tiles written: their caches are dropped
    assert ledger.cache_bytes == 0 and ledger.live_bytes == 2 * cells
    a.known_cells(1)
    a.release()                      # freed tiles free their caches too
    b.release()
    assert ledger.live_bytes == 0 and ledger.cache_bytes == 0 and ledger.live_tiles == 0
    assert ledger.peak_bytes == 2 * cells + cache


def _small_setup(mode: str, J: int = 8):
    import jax
    from cached_runs import shared_run

    from gslam_jax import rbpf
    from gslam_jax.driver.observations import local_observations
    from gslam_jax.driver.sizing import map_extent

    run = shared_run(24, seed=1)  # also compare's run (the ``compared`` fixture)
    obs = local_observations(run, 1e-4)
    L = obs.shape[1]
    probe = rbpf.FilterConfig(J, (8, 8), (0.0, 0.0), 0.16, L, unknown_cells=mode)
    ext = map_extent(run.vo_poses(), L, 0.16, 1.0, probe.window)
    cfg = rbpf.FilterConfig(J, ext.shape, ext.origin, 0.16, L, unknown_cells=mode,
                            unknown_samples=16, resample_ratio=0.9).validate()
    params = rbpf.FilterParams(beta_prev=jax.numpy.float32(0.05))  # JAX scalars, as compare's
    return run, obs, cfg, jax.random.key(2), params


def test_tiled_run_is_numpy_only_and_its_ledger_holds_everything():
    """With its draws made beforehand (``draw_noise``) the reference's loop, which ``compare``
    times, copies nothing from JAX; the ledger's bytes are those of the live tiles and caches."""
    import jax

    from gslam_jax.tiled.reference import draw_noise, run_tiled

    run, obs, cfg, key, params = _small_setup("sample")
    draws = draw_noise(key, run.obs_index, cfg)
    with jax.transfer_guard("disallow"):
        out = run_tiled(key, params, run.controls, run.obs_index, obs, cfg, 16 * 0.16,
                        draws=draws)
    again = run_tiled(key, params, run.controls, run.obs_index, obs, cfg, 16 * 0.16)
    np.testing.assert_array_equal(out.log_w, again.log_w)
    np.testing.assert_array_equal(out.pose, again.pose)
    np.testing.assert_array_equal(out.memory_bytes, again.memory_bytes)
    assert out.resampled.any() and len(out.update_seconds) == run.num_local_maps
    tiles = {id(t): t for m in out.final.maps for t in m.tiles.values()}
    ledger = out.final.ledger
    assert ledger.live_tiles == len(tiles)
    assert ledger.cache_bytes == sum(t.cache_nbytes for t in tiles.values()) > 0
    assert ledger.live_bytes == sum(t.nbytes + t.cache_nbytes for t in tiles.values())
    assert out.peak_bytes >= out.memory_bytes.max()


@pytest.fixture(scope="module")
def compared():
    """One ``compare`` of the small run (8 particles, "ignore"), made once for the two tests
    that read it: with the tiled run wrapped (it must get its draws made beforehand and copy
    nothing from JAX), the dense run's output kept, XLA_FLAGS capped at AVX (set after the
    backend started, so only the labels change) and the printout captured."""
    import jax

    from gslam_jax.app import compare as C
    from gslam_jax.config import Config, FilterSection, MapSection

    jax.devices()  # the backend starts here, before XLA_FLAGS changes (XLA reads it at start)
    real_tiled, real_dense = C.run_tiled, C.run_dense
    seen: dict = {"draws": []}

    def timed_tiled(*args, **kwargs):
        seen["draws"].append(kwargs.get("draws") is not None)
        with jax.transfer_guard("disallow"):
            return real_tiled(*args, **kwargs)

    def kept_dense(*args, **kwargs):
        seen["dense"] = real_dense(*args, **kwargs)
        return seen["dense"]

    text = io.StringIO()
    with pytest.MonkeyPatch.context() as mp, contextlib.redirect_stdout(text):
        mp.setattr(C, "run_tiled", timed_tiled)
        mp.setattr(C, "run_dense", kept_dense)
        mp.setenv("XLA_FLAGS", "--xla_cpu_max_isa=AVX")
        run, *_ = _small_setup("ignore")
        config = Config(filter=FilterSection(resample_ratio=0.9, unknown_cells="ignore"),
                        map=MapSection(margin=1.0))
        res = C.compare(run, config, particles=8)
    return run, res, text.getvalue(), seen


def test_compare_times_fairly_and_names_its_figures(compared):
    """The timed tiled run gets its draws made beforehand (no JAX copy inside); the dense
    memory is named for what it is (fixed state arrays); the update-alone ratio divides the
    tiled updates that did not resample by the dense update alone; an ISA cap in XLA_FLAGS
    labels the dense column."""
    from gslam_jax.app import compare as C

    assert C.dense_label("") == "dense (JAX)"
    assert C.dense_label("--xla_cpu_max_isa=AVX --xla_foo=1") == "dense (JAX, AVX only)"
    _, res, text, seen = compared
    assert seen["draws"] == [True]  # one tiled run, given its draws
    assert "dense (JAX, AVX only)" in text and "XLA_FLAGS: --xla_cpu_max_isa=AVX" in text
    d, t = res["dense"], res["tiled"]
    assert "peak_MB" not in d and d["state_MB"] > 0 and t["draw_seconds"] > 0
    assert d["xla_cpu_max_isa"] == "AVX"
    n_rs, M = res["tiled_resamplings"], res["updates"]
    assert 0 < n_rs < M, (n_rs, M)
    assert res["speed_ratio_update_alone"] == (t["seconds_per_update_without_resampling"]
                                               / d["update_alone_seconds"])
    np.testing.assert_allclose(n_rs * t["seconds_per_update_that_resampled"]
                               + (M - n_rs) * t["seconds_per_update_without_resampling"],
                               M * t["seconds_per_update"], rtol=1e-9)


if __name__ == "__main__":
    print(json.dumps(_equivalence()))
