"""The dense filter on a small hand-built world with known truth."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from synthetic import World, make_run

from gslam_jax import rbpf
from gslam_jax.config import Config, FilterSection, MotionSection
from gslam_jax.driver import observations, sizing, slam
from gslam_jax.driver.results import SlamResult
from gslam_jax.rbpf import unknown
from gslam_jax.rbpf.cells import obs_from_stats
from gslam_jax.rbpf.placement import observation_cells
from gslam_jax.rbpf.importance import _log_importance, log_importance
from gslam_jax.rbpf.types import CPU_BLOCK_CELLS
from gslam_jax.vo.localmap import LocalMapParams, points_to_stats

RES = 0.16
LM = LocalMapParams(resolution=RES, max_range=5.0, cells=64)


# Compilation, not running, is what these tests spend: runs are built once per module and
# shared, the eager updates are jitted (one compile per config instead of one per primitive)
# and tests that check different properties of the same filter run share that run.
_make_run = functools.lru_cache(make_run)
_observe = jax.jit(rbpf.observe, static_argnames=("cfg",))
_step = jax.jit(rbpf.step, static_argnames=("cfg",))


def _cfg(J, mode="ignore", **kw):
    kw.setdefault("tempering", "fixed")  # the paper's weights (eqs. 26, 30-31) unscaled
    return rbpf.FilterConfig(num_particles=J, map_shape=(256, 256), map_origin=(-20.48, -20.48),
                             resolution=RES, local_size=64, unknown_cells=mode, **kw)


def _local_obs(world, pose, seed):
    pts = world.observe(np.asarray(pose, float), np.random.default_rng(seed), n=30000)
    stats, _ = points_to_stats(pts, LM)
    return jnp.asarray(obs_from_stats(stats, 1e-6), jnp.float32)


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["ignore", "sample"])
def test_particle_nearest_truth_gains_weight(mode):
    """First observation builds the same map for all particles; the second, taken from the true
    pose, must favour the particle nearest the truth over ones displaced by VO drift."""
    world = World(3)
    truth = np.array([0.3, -0.2, 0.4])
    J = 9
    cfg = _cfg(J, mode, resample_ratio=0.0)
    params = rbpf.FilterParams()
    state = rbpf.init(cfg, jnp.asarray(truth, jnp.float32))
    noise = rbpf.update_noise(jax.random.key(0), cfg)
    state, _ = _observe(state, _local_obs(world, truth, 1), noise, params, cfg)
    offsets = np.array([[0, 0, 0], [0.5, 0, 0], [-0.5, 0, 0], [0, 0.5, 0], [0, -0.5, 0],
                        [0.3, 0.3, 0.05], [0, 0, 0.1], [0, 0, -0.1], [1.0, 0.0, 0.0]])
    state = state._replace(pose=jnp.asarray(truth + offsets, jnp.float32))
    state, info = _observe(state, _local_obs(world, truth, 2), noise, params, cfg)
    w = np.exp(np.asarray(info.log_w))
    assert int(np.argmax(w)) == 0
    assert w[0] > 0.5
    assert w[0] > 3 * np.sort(w)[-2]


@pytest.mark.slow
def test_best_particle_survives_resampling():
    """After a resampling every weight is equal, so the best particle must be the one that was
    best before it: the same update with and without resampling must name the same pose, also
    on the frames that follow without an update."""
    world = World(3)
    truth = np.array([0.3, -0.2, 0.4])
    J = 9
    params = rbpf.FilterParams()
    keep_cfg, resample_cfg = _cfg(J, resample_ratio=0.0), _cfg(J, resample_ratio=2.0)
    state = rbpf.init(keep_cfg, jnp.asarray(truth, jnp.float32))
    noise = rbpf.update_noise(jax.random.key(0), keep_cfg)
    state, _ = _observe(state, _local_obs(world, truth, 1), noise, params, keep_cfg)
    offsets = np.array([[1.0, 0, 0], [0.5, 0, 0], [-0.5, 0, 0], [0, 0.5, 0], [0, -0.5, 0],
                        [0.3, 0.3, 0.05], [0, 0, 0.1], [0, 0, 0], [0, 0, -0.1]])
    state = state._replace(pose=jnp.asarray(truth + offsets, jnp.float32))
    obs = _local_obs(world, truth, 2)
    kept, kept_info = _observe(jax.tree.map(jnp.copy, state), obs, noise, params, keep_cfg)
    resampled, info = _observe(state, obs, noise, params, resample_cfg)
    assert bool(info.resampled) and not bool(kept_info.resampled)
    assert np.ptp(np.asarray(info.log_w)) == 0.0  # equal weights: argmax would say slot 0
    assert int(np.argmax(kept_info.log_w)) == 7 == int(kept.best)
    np.testing.assert_array_equal(resampled.pose[resampled.best], state.pose[7])
    moved, moved_info = _step(jax.random.key(1), resampled, jnp.zeros(3), None, params,
                              resample_cfg)
    assert int(moved_info.best) == int(resampled.best) == int(moved.best)


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["ignore", "sample"])
def test_without_map_updates_the_weights_stay_uniform(mode):
    run, _ = _make_run(seed=1, steps=30)
    cfg = _cfg(16, mode, update_map=False)
    obs = jnp.asarray(observations.local_observations(run, 1e-6))
    out = rbpf.run_filter(jax.random.key(0), rbpf.FilterParams(),
                          jnp.asarray(run.controls, jnp.float32), jnp.asarray(run.obs_index),
                          obs, cfg)
    np.testing.assert_allclose(np.exp(np.asarray(out.infos.log_w)), 1 / 16, rtol=1e-5)
    assert not np.asarray(out.infos.resampled).any()


def _config(J=32, mode="sample", seed=0):
    return dataclasses.replace(Config(),
                               filter=FilterSection(particles=J, unknown_cells=mode, seed=seed),
                               motion=MotionSection(alpha_theta_d=0.02))


@functools.lru_cache
def _loop_slam(seed: int = 0, chunk: int = 512) -> SlamResult:
    """``run_slam`` of the 80-step loop with VO heading drift, 64 particles, filter seed
    ``seed``: one compiled scan per chunk length, shared by the tests below."""
    run, _ = _make_run(seed=4, steps=80, drift=0.004)
    return slam.run_slam(run, _config(J=64, seed=seed), chunk=chunk)


@pytest.mark.slow
def test_same_seed_is_bit_identical_and_seeds_differ():
    a = _loop_slam(seed=0)
    b = _loop_slam(seed=0, chunk=7)  # chunking (and padding 80 to 84) must not change anything
    c = _loop_slam(seed=1)
    np.testing.assert_array_equal(a.best_path, b.best_path)
    np.testing.assert_array_equal(a.ess, b.ess)
    np.testing.assert_array_equal(a.kmap, b.kmap)
    assert not np.array_equal(a.best_path, c.best_path)


@pytest.mark.slow
def test_slam_corrects_vo_heading_drift_on_a_loop():
    run, _ = _make_run(seed=4, steps=80, drift=0.004)
    res = _loop_slam(seed=0)
    gt = run.ground_truth[:, :2]
    vo_err = np.linalg.norm(res.vo_path[:, :2] - gt, axis=1)
    slam_err = np.linalg.norm(res.best_path[:, :2] - gt, axis=1)
    assert res.resampled.any()
    assert vo_err[-1] > 0.8
    assert slam_err[-1] < 0.5 * vo_err[-1]
    assert res.extent_violations == 0


@pytest.mark.slow
def test_footprints_leaving_the_map_are_counted_not_wrapped():
    run, _ = _make_run(seed=1, steps=30)
    cfg = rbpf.FilterConfig(num_particles=4, map_shape=(112, 112), map_origin=(-2.0, -9.0),
                            resolution=RES, local_size=64, unknown_cells="ignore")
    obs = jnp.asarray(observations.local_observations(run, 1e-6))
    out = rbpf.run_filter(jax.random.key(0), rbpf.FilterParams(),
                          jnp.asarray(run.controls, jnp.float32), jnp.asarray(run.obs_index),
                          obs, cfg)
    assert int(np.sum(out.infos.extent_violations)) > 0


def test_observation_cells_match_float64_geometry():
    """Each local cell centre, rotated and translated in float64, lands in the same map cell
    (up to float32 rounding at cell borders), and off-map cells are flagged, not wrapped."""
    rng = np.random.default_rng(0)
    L, H, W = 16, 40, 48
    cfg = rbpf.FilterConfig(1, (H, W), (-3.0, -2.0), RES, L, unknown_cells="ignore")
    centre = (np.arange(L) - L // 2 + 0.5) * RES
    a, b = np.meshgrid(centre, centre, indexing="ij")
    mismatches = 0
    for _ in range(50):
        pose = np.array([rng.uniform(-3.5, 3.5), rng.uniform(-2.5, 6.0),
                         rng.uniform(-np.pi, np.pi)])
        flat, on_map = map(np.asarray, observation_cells(
            jnp.asarray(pose, jnp.float32), jnp.arange(L * L, dtype=jnp.int32), cfg))
        c, s = np.cos(pose[2]), np.sin(pose[2])
        gi = np.floor((pose[0] + c * a - s * b - cfg.map_origin[0]) / RES).astype(int).ravel()
        gj = np.floor((pose[1] + s * a + c * b - cfg.map_origin[1]) / RES).astype(int).ravel()
        inside = (gi >= 0) & (gi < H) & (gj >= 0) & (gj < W)
        mismatches += int(np.sum(inside != on_map))
        both = inside & on_map
        mismatches += int(np.sum(flat[both] != (gi * W + gj)[both]))
        assert np.all(flat[~on_map] == H * W)
    assert mismatches <= 0.002 * 50 * L * L


_OBLIQUE_ALIASES = pytest.mark.xfail(
    strict=True, reason="known: a local map on the robot's lattice ([localmap] lattice = "
    "'robot') aliases at oblique headings, so results depend on the map frame's orientation; "
    "the map's lattice avoids it (next test; docs/notebook/results.md, 'The map frame's orientation')")


@pytest.mark.parametrize("heading", [0.0, np.pi / 2,
                                     pytest.param(np.pi / 4, marks=_OBLIQUE_ALIASES)])
def test_a_turned_local_map_lands_one_cell_per_map_cell(heading):
    """Placement should not depend on the map frame's orientation. A local map on the robot's
    lattice along the map's axes has a map cell for every local cell; turned by 45 degrees a
    third of them share one with another local cell (and as many map cells beneath stay
    empty). On the KITTI clip the final drift on the robot's lattice was 0.81 % with the frame
    turned by 22.5 degrees against 0.35 % (docs/notebook/results.md)."""
    L = 64
    cfg = rbpf.FilterConfig(1, (200, 200), (-16.0, -16.0), RES, L, unknown_cells="ignore")
    flat, _ = observation_cells(jnp.asarray([0.03, 0.05, heading], jnp.float32),
                                jnp.arange(L * L, dtype=jnp.int32), cfg)
    _, counts = np.unique(np.asarray(flat), return_counts=True)
    shared = np.sum(counts[counts > 1]) / (L * L)
    assert shared < 0.01, f"heading {np.degrees(heading):.0f} deg: {shared:.0%} share a cell"


@pytest.mark.parametrize("correction_deg", [0.0, 1.0, -2.0])
def test_a_map_lattice_local_map_lands_one_cell_per_map_cell_at_any_heading(correction_deg):
    """[localmap] lattice = "map": the local map's lattice is turned by minus the VO heading
    (here 45 degrees), so a particle whose heading differs from the VO's by a correction of a
    degree or two still places its local cells one to a map cell (the oblique case of the
    test above, which fails on the robot's lattice)."""
    L = 64
    cfg = rbpf.FilterConfig(1, (200, 200), (-16.0, -16.0), RES, L, unknown_cells="ignore")
    vo_heading = np.pi / 4
    pose = jnp.asarray([0.03, 0.05, vo_heading + np.radians(correction_deg)], jnp.float32)
    flat, _ = observation_cells(pose, jnp.arange(L * L, dtype=jnp.int32), cfg, -vo_heading)
    _, counts = np.unique(np.asarray(flat), return_counts=True)
    shared = np.sum(counts[counts > 1]) / (L * L)
    assert shared < 0.01, f"correction {correction_deg} deg: {shared:.1%} share a cell"


def test_update_adds_every_on_map_cell_once():
    """Eq. 14 through the scatter: the map gains exactly the on-map local statistics."""
    L = 16
    cfg = rbpf.FilterConfig(1, (40, 40), (0.0, 0.0), RES, L, unknown_cells="ignore",
                            resample_ratio=0.0)
    rng = np.random.default_rng(1)
    k = rng.integers(0, 5, (L, L)).astype(np.float32)
    local = jnp.asarray(np.stack([k, 0.1 * k], -1))
    for pose in ([3.2, 3.2, 0.7], [0.3, 3.2, 2.0]):  # inside; half off the map's top edge
        state = rbpf.init(cfg)._replace(pose=jnp.asarray([pose], jnp.float32))
        noise = rbpf.update_noise(jax.random.key(0), cfg)
        new, info = _observe(state, local, noise, rbpf.FilterParams(), cfg)
        _, on_map = observation_cells(state.pose[0], jnp.arange(L * L, dtype=jnp.int32), cfg)
        expected = float(np.sum(k.ravel()[np.asarray(on_map)]))
        assert float(jnp.sum(new.maps.k)) == expected
        assert int(info.extent_violations) == int(expected < k.sum())
    assert expected < k.sum()  # the second pose really left the map


@pytest.mark.slow
def test_empty_local_maps_leave_weights_unchanged_and_are_counted():
    run, _ = _make_run(seed=1, steps=30)
    run = run._replace(local_maps=np.zeros_like(run.local_maps))
    res = slam.run_slam(run, _config(J=8))
    assert res.empty_observations == run.num_local_maps
    assert not res.resampled.any()
    np.testing.assert_allclose(res.ess, 8.0, rtol=1e-5)


J_SHARED = 11  # the CPU default's block shape below: blocks of 3, 3, 3 and a tail of 2


def _shared_base(mode: str) -> rbpf.FilterConfig:
    """The filter of the compaction, particle-block and written-rows tests, on one run."""
    run, _ = _make_run(seed=2, steps=30)
    return rbpf.FilterConfig(J_SHARED, (160, 160), (-8.0, -12.8), RES, run.local_maps.shape[1],
                             unknown_cells=mode, unknown_samples=64, resample_ratio=0.9)


@functools.lru_cache
def _shared_run(mode: str, observed_cells: int, particle_block: int) -> rbpf.RunOutput:
    """One run_filter of the seed-2 run per (mode, M, block), compiled and run once per module;
    the tests read different properties of the same runs."""
    run, _ = _make_run(seed=2, steps=30)
    cfg = _shared_base(mode)._replace(observed_cells=observed_cells,
                                      particle_block=particle_block)
    return rbpf.run_filter(jax.random.key(4), rbpf.FilterParams(),
                           jnp.asarray(run.controls, jnp.float32), jnp.asarray(run.obs_index),
                           jnp.asarray(observations.local_observations(run, 1e-6)), cfg)


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["ignore", "sample"])
def test_compacted_update_equals_full_and_reports_overflow(mode):
    """Evaluating only the observed cells (observed_cells = M) gives the same weights and maps
    as evaluating all L*L; a cap below the observed count is reported, not silent."""
    run, _ = _make_run(seed=2, steps=30)
    obs = jnp.asarray(observations.local_observations(run, 1e-6))
    L = obs.shape[1]
    M = sizing.observed_cells(run)
    assert M < L * L
    base = _shared_base(mode)
    full, compact = (_shared_run(mode, cap, J_SHARED) for cap in (0, M))
    assert int(np.sum(full.infos.resampled)) >= 1  # the maps were copied too
    np.testing.assert_allclose(compact.infos.log_w, full.infos.log_w, atol=1e-5)
    np.testing.assert_array_equal(compact.final_state.maps.k, full.final_state.maps.k)
    assert int(np.sum(compact.infos.dropped_cells)) == 0
    small = base._replace(observed_cells=8)
    state = rbpf.init(small)
    _, info = _observe(state, obs[0], rbpf.update_noise(jax.random.key(0), small),
                       rbpf.FilterParams(), small)
    assert int(info.dropped_cells) == int(np.sum(np.asarray(obs[0, ..., 0]) > 0)) - 8 > 0


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["ignore", "sample"])
def test_update_in_particle_blocks_equals_one_pass(mode):
    """Reading, weighing and writing the particles in blocks (3 of 3 and a tail of 2, the CPU
    default's shape) gives the same weights, resampling and maps as one pass over all of them,
    and the auto choice is one pass on accelerators, cache-sized blocks on a CPU."""
    run, _ = _make_run(seed=2, steps=30)
    M = sizing.observed_cells(run)
    one, blocks = (_shared_run(mode, M, block) for block in (J_SHARED, 3))
    assert int(np.sum(one.infos.resampled)) >= 1
    np.testing.assert_array_equal(blocks.infos.resampled, one.infos.resampled)
    np.testing.assert_array_equal(blocks.infos.ancestors, one.infos.ancestors)
    # float32 sums of a different fusion: a few ulp (the tiled equivalence tolerance is 1e-4)
    np.testing.assert_allclose(blocks.infos.log_w, one.infos.log_w, atol=1e-4)
    np.testing.assert_array_equal(blocks.final_state.maps.k, one.final_state.maps.k)
    np.testing.assert_allclose(blocks.final_state.maps.S, one.final_state.maps.S, rtol=1e-6)
    np.testing.assert_array_equal(blocks.final_state.maps.known_bits,
                                  one.final_state.maps.known_bits)
    if mode == "sample":  # the segment counts kept beside the bits are the bits' own
        np.testing.assert_array_equal(one.final_state.maps.known_counts,
                                      unknown.segment_counts(one.final_state.maps.known_bits))
        assert int(one.final_state.maps.known_counts.sum()) == int(
            np.sum(np.asarray(one.final_state.maps.k) > 0))

    auto = CPU_BLOCK_CELLS // 4096 if jax.default_backend() == "cpu" else 200
    big = _shared_base(mode)._replace(num_particles=200, observed_cells=4096)
    assert big.update_block == auto
    assert big._replace(particle_block=7).update_block == 7
    with pytest.raises(ValueError, match="particle_block"):
        big._replace(particle_block=-1).validate()


def test_filter_config_resolves_the_automatic_particle_block_on_the_host():
    """``[filter] particle_block = 0`` becomes the default backend's block size when the config
    is built, so the static config the update is traced with carries it; a set size is kept."""
    run, _ = _make_run(seed=2, steps=30)
    cfg = sizing.filter_config(_config(J=200, mode="ignore"), run)
    auto = CPU_BLOCK_CELLS // cfg.max_observed if jax.default_backend() == "cpu" else 200
    assert cfg.particle_block == min(auto, 200) > 0
    config = _config(J=200, mode="ignore")
    config = dataclasses.replace(config, filter=dataclasses.replace(config.filter,
                                                                    particle_block=7))
    assert sizing.filter_config(config, run).particle_block == 7


@pytest.mark.parametrize("M", [200, 256])
def test_sample_mode_borrows_draw_c_mod_d_from_the_draws_themselves(M):
    """Eq. 31 with the D draws passed as they are (the layout the update uses) equals eq. 31
    with every cell's borrowed draw spelled out (cell c takes draw c mod D), padded or not."""
    rng = np.random.default_rng(M)
    D = 64
    k = rng.integers(0, 12, M).astype(np.float32)
    S = (k * rng.gamma(2.0, 0.01, M)).astype(np.float32)
    kp = np.where(rng.uniform(size=M) < 0.5, rng.integers(1, 40, M), 0).astype(np.float32)
    Sp = (kp * rng.gamma(2.0, 0.01, M)).astype(np.float32)
    kd = np.where(rng.uniform(size=D) < 0.8, rng.integers(1, 400, D), 0).astype(np.float32)
    Sd = (kd * rng.gamma(2.0, 0.02, D)).astype(np.float32)
    params = rbpf.FilterParams(beta_prev=0.3, beta_new=0.7)
    # jitted, as the update runs them: one compile each instead of one per eager primitive
    spelled = jax.jit(log_importance, static_argnums=8)(
        k, S, kp, Sp, kd[np.arange(M) % D], Sd[np.arange(M) % D], jnp.bool_(True), params,
        "sample")
    from gslam_jax.rbpf.cells import log_v_obs
    drawn = jax.jit(_log_importance, static_argnums=8)(
        jnp.asarray(k), jnp.asarray(S), jnp.asarray(kp), jnp.asarray(Sp), jnp.asarray(kd),
        jnp.asarray(Sd), jnp.bool_(True), params, "sample",
        log_v_obs(jnp.asarray(k), jnp.asarray(S)))
    np.testing.assert_allclose(float(drawn), float(spelled), rtol=1e-5)
    assert float(spelled) != 0.0


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["ignore", "sample"])
def test_written_rows_cover_every_written_cell(mode):
    """DenseMaps.rows, which bounds what resampling copies, holds every map row with data
    after a run with resampling (the compaction test's full run)."""
    out = _shared_run(mode, 0, J_SHARED)
    assert int(np.sum(out.infos.resampled)) >= 2
    lo, hi = (int(v) for v in out.final_state.maps.rows)
    written = np.nonzero(np.asarray(out.final_state.maps.k).any(axis=(0, 2)))[0]
    assert written.size and lo <= written.min() and written.max() < hi <= 160
    assert hi - lo < 160  # the bound is useful, not the whole map
