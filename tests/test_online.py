"""The live API (``online.Online``): frame by frame it reproduces the batch run bit for bit on
the same frames, seed and map; one compilation for every frame; fixed extent, refused edge."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from synthetic import World, truth_and_controls

from gslam_jax.config import Config, ConfigError, FilterSection, LocalMapSection
from gslam_jax.driver import sizing, slam
from gslam_jax.driver.online import MapEdgeError, Online, online_step
from gslam_jax.errors import InputError
from gslam_jax.gridmap import turn_poses
from gslam_jax.run import Run, integrate_controls
from gslam_jax.vo.localmap import build_local_maps, localmap_params

CONFIG = Config(filter=FilterSection(particles=8, seed=3),
                localmap=LocalMapSection(max_range=5.0, travel=1.0))


@pytest.fixture(scope="module")
def frames():
    """Points per frame, VO controls with a heading drift, and the batch Run built from them."""
    world, rng = World(0), np.random.default_rng(1)
    gt, u_true = truth_and_controls("loop", 30)
    u = u_true + np.array([0.0, 0.0, 0.004])
    points = [world.observe(p, rng) for p in gt]
    obs_index, local_maps, *_ = build_local_maps(integrate_controls(u), points,
                                                localmap_params(CONFIG))
    run = Run(controls=u, obs_index=obs_index, local_maps=local_maps, resolution=0.16,
              timestamps=np.arange(30) * 0.2, ground_truth=gt, initial_pose=np.zeros(3))
    return run, points


@pytest.fixture(scope="module")
def batch(frames):
    run, _ = frames
    return slam.run_slam(run, CONFIG), slam.run_filter_config(run, CONFIG)



def _check_paths(live: Online, res) -> None:
    """Online's path by every estimate, and by the config's, is the batch run's."""
    want = {"best": res.best_path, "mean": res.mean_pose, "smoothed": res.smoothed_path,
            "steps": res.steps_path, "mode": res.mode_path, "mode_mean": res.mode_mean_path,
            "local_steps": res.local_steps_path}
    for estimate, path in want.items():
        np.testing.assert_allclose(live.path(estimate), path, rtol=0, atol=1e-9)
    np.testing.assert_allclose(live.path(), res.path, rtol=0, atol=1e-9)
    with pytest.raises(ConfigError, match="estimate must be one of"):
        live.path("median")

def test_online_reproduces_the_batch_run_with_one_compilation(frames, batch):
    run, points = frames
    res, cfg = batch
    live = Online(CONFIG, filter_config=cfg)
    compiled = []
    for t in range(run.num_frames):
        m = run.obs_index[t]
        out = live.push(run.controls[t], run.local_maps[m] if m >= 0 else None,
                        run.timestamps[t])
        np.testing.assert_array_equal(out.pose, res.best_pose[t])
        compiled.append(online_step._cache_size())
    assert compiled[-1] == compiled[0]  # every frame after the first reuses its compilation
    np.testing.assert_array_equal(np.stack(live.mean), res.mean_pose)
    _check_paths(live, res)
    grid = live.map()
    np.testing.assert_array_equal(grid.k, res.kmap)
    np.testing.assert_array_equal(grid.S, res.smap)
    assert grid.origin == res.map_origin
    p = live.particles()
    assert p.pose.shape == (8, 3) and p.weight.sum() == pytest.approx(1.0, abs=1e-5)

    # points fused into local maps by Online itself: the same frames, the same poses
    fused = Online(CONFIG, filter_config=cfg)
    for t in range(run.num_frames):
        fused.push_points(run.controls[t], points[t], run.timestamps[t])
    assert online_step._cache_size() == compiled[0]
    np.testing.assert_array_equal(np.stack(fused.best), res.best_pose)

    s = live.stats()
    assert s.frames == 30 and s.updates == int(np.sum(run.obs_index >= 0))
    assert s.log_seconds == pytest.approx(run.timestamps[-1] - run.timestamps[0])
    assert s.realtime_factor == pytest.approx(s.log_seconds / s.frame_latency.sum())
    assert len(s.update_latency) == int(np.sum(run.obs_index[1:] >= 0))


def test_an_automatic_shared_pool_grows_as_the_frames_come(frames, batch, monkeypatch):
    """On the shared store with an automatic pool that starts too small (200 tiles of 16 x 16
    cells; the run holds more at once), Online grows it between frames, says so, and still
    reproduces the (dense) batch run."""
    from gslam_jax.rbpf import maps

    run, _ = frames
    res, cfg = batch
    real = maps.pool_tiles
    monkeypatch.setattr(maps, "pool_tiles", lambda c: c.pool_tiles or min(real(c), 200))
    live = Online(CONFIG, filter_config=cfg._replace(store="shared", tile=16, pool_tiles=0))
    with pytest.warns(maps.MapStoreNotice, match=r"^frame \d+: .*pool grew from 200 to"):
        for t in range(run.num_frames):
            m = run.obs_index[t]
            live.push(run.controls[t], run.local_maps[m] if m >= 0 else None, run.timestamps[t])
    assert live.cfg.pool_tiles > 200 and int(live.state.maps.peak) > 200  # and was needed
    np.testing.assert_array_equal(np.stack(live.best), res.best_pose)
    np.testing.assert_array_equal(live.map().k, res.kmap)


def test_a_window_store_history_grows_as_the_local_maps_come(frames, batch, monkeypatch):
    """On the window store with an automatic history ([map] pool_tiles = 0) that starts at 8
    local maps (the run has 15), Online doubles it when it is full, says so, and still reproduces the
    (dense) batch run; a history the config fixes does not grow."""
    from gslam_jax.rbpf import maps

    run, _ = frames
    res, cfg = batch
    monkeypatch.setattr(maps, "LIVE_HISTORY", 8)
    live = Online(CONFIG, filter_config=cfg._replace(store="window", pool_tiles=0))
    assert live.cfg.pool_tiles == 8
    with pytest.warns(maps.MapStoreNotice, match=r"^frame \d+: .*history grew from 8 to 16 "):
        for t in range(run.num_frames):
            m = run.obs_index[t]
            live.push(run.controls[t], run.local_maps[m] if m >= 0 else None, run.timestamps[t])
    updates = int(np.sum(run.obs_index >= 0))
    assert int(live.state.maps.count) == updates > 8
    assert live.cfg.pool_tiles == 16
    np.testing.assert_array_equal(np.stack(live.best), res.best_pose)
    np.testing.assert_array_equal(live.map().k, res.kmap)

    fixed = Online(dataclasses.replace(CONFIG, map=dataclasses.replace(CONFIG.map, pool_tiles=2)),
                   filter_config=cfg._replace(store="window", pool_tiles=2))
    with pytest.raises(maps.WindowStoreError, match="history"):
        for t in range(run.num_frames):
            m = run.obs_index[t]
            fixed.push(run.controls[t], run.local_maps[m] if m >= 0 else None,
                       run.timestamps[t])


def test_a_given_extent_sizes_the_filter_as_the_batch_run(frames, batch):
    run, _ = frames
    _, cfg = batch
    live = Online(CONFIG, sizing.MapExtent(cfg.map_origin, cfg.map_shape),
                  local_size=cfg.local_size, observed_cells=cfg.observed_cells)
    assert live.cfg == cfg


def test_a_size_in_metres_covers_the_square_around_the_start():
    start = np.array([3.0, -2.0, 0.5])
    live = Online(CONFIG, 10.0, start_pose=start)
    cfg = live.cfg
    lo = np.asarray(cfg.map_origin)
    hi = lo + np.asarray(cfg.map_shape) * cfg.resolution
    reach = 5.0 + 0.5 * cfg.window * cfg.resolution  # half the side plus a rotated local map
    centre = turn_poses(start, -live.heading)[:2]  # the square on the map's axes
    assert (lo <= centre - reach + 1e-9).all() and (hi >= centre + reach - 1e-9).all()
    assert (hi - lo < 2 * reach + 8 * cfg.resolution + 1e-9).all()  # rounded up to 8 cells
    np.testing.assert_allclose(live.particles().pose, np.tile(start, (8, 1)), atol=1e-6)


def test_the_map_edge_is_refused_naming_the_frame(frames, batch):
    """The batch run's map (about 41 m across, around a loop 5 m across; its compiled step is
    the first test's) with the loop driven at ten times its size: a local map reaches past the
    edge."""
    run, _ = frames
    live = Online(CONFIG, filter_config=batch[1])
    with pytest.raises(MapEdgeError, match=r"frame \d+: the local map reached past the edge "
                                           r"of the live map .* give Online a larger "
                                           r"map_extent"):
        for t in range(run.num_frames):
            m = run.obs_index[t]
            live.push(run.controls[t] * [10.0, 10.0, 1.0],
                      run.local_maps[m] if m >= 0 else None)


def test_bad_frames_are_refused_before_the_filter(frames, batch):
    run, _ = frames
    live = Online(CONFIG, filter_config=batch[1])
    with pytest.raises(InputError, match=r"frame 0: control must be 3 finite numbers"):
        live.push([0.1, np.nan, 0.0])
    L = batch[1].local_size
    with pytest.raises(InputError, match=rf"frame 0: local_map must be \[{L}, {L}, 3\]"):
        live.push([0.1, 0.0, 0.0], np.zeros((4, 4, 3)))
    live.push([0.1, 0.0, 0.0], None, 1.0)
    with pytest.raises(InputError, match=r"frame 1: time 1.0 s is not after the previous "
                                         r"frame's 1.0 s"):
        live.push([0.1, 0.0, 0.0], None, 1.0)
    with pytest.raises(ConfigError, match="start_pose must be 3 finite numbers"):
        Online(CONFIG, 10.0, start_pose=[0.0, 1.0])
    with pytest.raises(ConfigError, match="either filter_config or map_extent"):
        Online(CONFIG, 10.0, filter_config=batch[1])


def test_a_range_noise_profile_is_estimated_as_the_frames_come(frames, batch, monkeypatch):
    """``[filter] range_noise = "profile"`` online: no whole run up front, so the profile is a
    running estimate (``RunningRangeNoise``). After n maps, n a power of two, it is the batch
    estimate of a run cut after those n maps; it changes the weights; one compilation."""
    import dataclasses

    from gslam_jax.driver import observations
    from gslam_jax.driver.observations import run_range_noise

    # 64 x 64 local maps, 15 of them; this world's variance does not grow with range, so the
    # profile is noise (not zero after 1, 2 and 4 maps, zero after 8)
    monkeypatch.setattr(observations, "RING_MIN_CELLS", 50)
    run, _ = frames
    _, cfg = batch
    config = dataclasses.replace(CONFIG, filter=dataclasses.replace(CONFIG.filter,
                                                                    range_noise="profile"))
    live, plain = Online(config, filter_config=cfg), Online(CONFIG, filter_config=cfg)
    assert live.range_noise is not None and not live.range_noise.any()
    assert plain.range_noise is None
    compiled, checked, nonzero = None, 0, 0
    for t in range(run.num_frames):
        m = int(run.obs_index[t])
        local = run.local_maps[m] if m >= 0 else None
        live.push(run.controls[t], local, run.timestamps[t])
        plain.push(run.controls[t], local, run.timestamps[t])
        compiled = compiled or online_step._cache_size()
        n = m + 1
        if m >= 0 and n & (n - 1) == 0:
            cut = run._replace(local_maps=run.local_maps[:n])
            np.testing.assert_array_equal(live.range_noise, run_range_noise(cut, config))
            checked += 1
            nonzero += bool(live.range_noise.any())
    assert checked == 4 and nonzero >= 1
    assert online_step._cache_size() == compiled  # a new profile is a new value, not a shape
    assert not np.array_equal(live.particles().weight, plain.particles().weight)


def test_map_lattice_local_maps_fused_online_reproduce_the_batch_run(frames):
    """[localmap] lattice = "map": Online.push_points bins each local map on the map's axes
    and hands its lattice angle to the filter, as the batch run of the Run built from the same
    points does (the loop turns through every heading)."""
    run0, points = frames
    config = dataclasses.replace(CONFIG, localmap=dataclasses.replace(CONFIG.localmap,
                                                                      lattice="map"))
    obs_index, local_maps, _, headings = build_local_maps(
        integrate_controls(run0.controls), points, localmap_params(config))
    assert np.ptp(headings) > 3.0  # the loop turns the lattice through every angle
    run = run0._replace(obs_index=obs_index, local_maps=local_maps, lattice_headings=headings)
    res = slam.run_slam(run, config)
    fused = Online(config, filter_config=slam.run_filter_config(run, config))
    for t in range(run.num_frames):
        fused.push_points(run.controls[t], points[t], run.timestamps[t])
    np.testing.assert_array_equal(np.stack(fused.best), res.best_pose)
    robot = slam.run_slam(run0, CONFIG)
    assert not np.array_equal(res.best_pose, robot.best_pose)  # the lattice changed the run


def test_on_the_start_axes_online_reproduces_the_batch_run(frames):
    """[map] axes = "start" with a turned start pose: Online runs on the robot's start axes
    as the batch run does (its "map" local lattice binned on them), and gives back its poses,
    path and particles in the frame and its map on those axes."""
    run0, points = frames
    start = np.array([0.4, -0.3, 0.7])
    config = dataclasses.replace(
        CONFIG, map=dataclasses.replace(CONFIG.map, axes="start"),
        localmap=dataclasses.replace(CONFIG.localmap, lattice="map"))
    obs_index, local_maps, _, headings = build_local_maps(
        integrate_controls(run0.controls, start), points, localmap_params(config), start)
    run = run0._replace(obs_index=obs_index, local_maps=local_maps, lattice_headings=headings,
                        initial_pose=start, ground_truth=None)
    res = slam.run_slam(run, config)
    assert res.map_heading == pytest.approx(0.7)
    cfg = slam.run_filter_config(run, config)
    live = Online(config, filter_config=cfg, start_pose=start)
    assert live.heading == pytest.approx(0.7)
    for t in range(run.num_frames):
        live.push_points(run.controls[t], points[t], run.timestamps[t])
    np.testing.assert_array_equal(np.stack(live.best), res.best_pose)
    np.testing.assert_array_equal(np.stack(live.mean), res.mean_pose)
    _check_paths(live, res)
    grid = live.map()
    np.testing.assert_array_equal(grid.k, res.kmap)
    assert grid.heading == pytest.approx(res.map_heading)
    best = live.particles().pose[int(np.argmax(live.particles().weight))]
    np.testing.assert_allclose(best, res.best_pose[-1], atol=1e-6)
    # the poses are the frame's: the first lies by the VO's first pose from the start
    vo = integrate_controls(run.controls, start)
    assert np.hypot(*(live.best[0][:2] - vo[0][:2])) < 0.05
    plain = Online(dataclasses.replace(config, map=dataclasses.replace(config.map, axes="frame")),
                   filter_config=cfg, start_pose=start)
    assert plain.heading == 0.0
