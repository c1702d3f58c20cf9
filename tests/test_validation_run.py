"""Run files that used to load (or crash later with a traceback): each is a RunError naming the
file, the field and, where it applies, the first bad frame."""

import numpy as np
import pytest
from synthetic import make_run

from gslam_jax.config import ConfigError
from gslam_jax.driver.sizing import check_float32_reach, map_extent
from gslam_jax.run import Run, RunError, integrate_controls, load_run, save_run, validate_run
from gslam_jax.run.checks import BLOCK_MAPS, MAX_SPEED, coordinate_limit, float32_limit, float32_spacing


@pytest.fixture(scope="module")
def run():
    return make_run(steps=15)[0]


def _save(tmp_path, run, **changes):
    fields = {k: v for k, v in run._asdict().items() if v is not None}
    fields.update(changes)
    np.savez(tmp_path / "bad.npz", **fields)
    return tmp_path / "bad.npz"


def _first_map_frame(run):
    """(frame, local map) of the first frame that carries a local map."""
    t = int(np.flatnonzero(run.obs_index >= 0)[0])
    return t, int(run.obs_index[t])


def test_nan_timestamp_names_the_frame(tmp_path, run):
    ts = run.timestamps.copy()
    ts[4] = np.nan
    with pytest.raises(RunError, match=r"bad\.npz: field 'timestamps': non-finite .* frame 4"):
        load_run(_save(tmp_path, run, timestamps=ts))


@pytest.mark.parametrize("value", [0.6, 0.5])  # frame 3 is at 0.6 s: equal, then earlier
def test_non_increasing_timestamps_name_the_frame(tmp_path, run, value):
    ts = run.timestamps.copy()
    ts[4] = value
    with pytest.raises(RunError, match=r"bad\.npz: field 'timestamps': not increasing at frame 4"):
        load_run(_save(tmp_path, run, timestamps=ts))


def test_nan_initial_pose(tmp_path, run):
    with pytest.raises(RunError, match=r"bad\.npz: field 'initial_pose': non-finite"):
        load_run(_save(tmp_path, run, initial_pose=np.array([0.0, np.nan, 0.0])))


def test_fractional_point_count_names_map_and_frame(tmp_path, run):
    t, m = _first_map_frame(run)
    maps = run.local_maps.copy()
    maps[m, 5, 6, 0] += 0.5
    with pytest.raises(RunError, match=rf"bad\.npz: field 'local_maps': non-integer point count "
                                       rf"n in local map {m} \(frame {t}\), cell \(5, 6\)"):
        load_run(_save(tmp_path, run, local_maps=maps))


def test_negative_variance_names_map_and_frame(tmp_path, run):
    t, m = _first_map_frame(run)
    maps = run.local_maps.copy()
    maps[m, 2, 3] = [4.0, 2.0, 0.5]  # n sum z^2 = 2 < (sum z)^2 = 4: used to be clipped to S = 0
    with pytest.raises(RunError, match=rf"bad\.npz: field 'local_maps': negative variance .* "
                                       rf"local map {m} \(frame {t}\), cell \(2, 3\)"):
        load_run(_save(tmp_path, run, local_maps=maps))


def test_rounding_in_the_variance_is_tolerated(tmp_path, run):
    maps = run.local_maps.copy()
    z = np.full(7, 0.1)  # identical heights: n sum z^2 - (sum z)^2 is 0 up to rounding
    maps[0, 0, 0] = [7, z.sum(), z @ z]
    maps[0, 0, 1] = [7, z.sum(), z @ z * (1 - 1e-12)]
    back = load_run(_save(tmp_path, run, local_maps=maps))
    np.testing.assert_array_equal(back.local_maps, maps)


def test_statistics_are_checked_block_by_block_as_one_array(run):
    """The checks take the local maps ``BLOCK_MAPS`` at a time: the first bad cell and the
    count are still those of all the maps, and float32 rounding is allowed only where every
    block holds float32 values."""
    base = run.local_maps.astype(np.float32).astype(np.float64)
    M = 3 * BLOCK_MAPS + 5
    maps = np.concatenate([base] * (M // len(base) + 1))[:M].copy()
    late, later = 2 * BLOCK_MAPS + 3, 3 * BLOCK_MAPS + 1
    bad = maps.copy()
    bad[later, 4, 5] = [4.0, 2.0, 0.5]
    bad[late, 2, 3] = [4.0, 2.0, 0.5]
    with pytest.raises(RunError, match=rf"negative variance .* local map {late} \(used by no "
                                       rf"frame\), cell \(2, 3\) \(2 cells in all\)"):
        validate_run(run._replace(local_maps=bad))
    # a deficit of 5e-6 relative: within float32 rounding at n = 7, beyond float64's
    near = maps.copy()
    near[late, 2, 3] = [7.0, np.float32(0.7), np.float32(0.07 * (1 - 1e-5))]
    validate_run(run._replace(local_maps=near))
    near[later, 0, 0] = [1.0, 0.1, 0.01]  # not float32 values: float64's tolerance for all
    with pytest.raises(RunError, match=rf"negative variance .* local map {late} .*cell \(2, 3\)"):
        validate_run(run._replace(local_maps=near))


def test_non_boolean_vo_failed(tmp_path, run):
    flags = np.zeros(run.num_frames)
    flags[2] = 0.5
    with pytest.raises(RunError, match=r"bad\.npz: field 'vo_failed': expected bool, got dtype float64"):
        load_run(_save(tmp_path, run, vo_failed=flags))


@pytest.mark.parametrize("value", [np.array([0.16, 0.16]), np.zeros((0,))])
def test_non_scalar_resolution(tmp_path, run, value):
    with pytest.raises(RunError, match=r"bad\.npz: field 'resolution': expected a scalar"):
        load_run(_save(tmp_path, run, resolution=value))


def _float32_accumulated(maps: np.ndarray, cells: int, seed: int = 0) -> np.ndarray:
    """``maps`` as float32, its first ``cells`` cells replaced by the statistics of 50-2000
    heights of 1.5 m +- 0.3 mm summed one by one in float32 (a float32 local-map builder)."""
    rng = np.random.default_rng(seed)
    out = maps.astype(np.float32)
    flat = out.reshape(-1, 3)
    for c in range(cells):
        z = (1.5 + rng.normal(0, 3e-4, rng.integers(50, 2000))).astype(np.float32)
        flat[c] = [z.size, np.cumsum(z, dtype=np.float32)[-1],
                   np.cumsum(z * z, dtype=np.float32)[-1]]
    return out


def test_float32_accumulated_statistics_load(tmp_path, run):
    """Before: a relative tolerance of 1e-6 whatever the dtype rejected about 3% of such cells
    (float32 rounding makes n sum z^2 - (sum z)^2 slightly negative when the spread is tiny)."""
    maps = _float32_accumulated(run.local_maps, 2000)
    n, sz, szz = (maps[..., c].astype(np.float64) for c in range(3))
    assert (n * szz - sz * sz < -1e-6 * (n * szz + sz * sz)).sum() > 10  # what was rejected
    back = load_run(_save(tmp_path, run, local_maps=maps))
    np.testing.assert_array_equal(back.local_maps, maps)
    assert back.local_maps.dtype == np.float64
    save_run(tmp_path / "again.npz", back)  # widened to float64, still float32 statistics
    np.testing.assert_array_equal(load_run(tmp_path / "again.npz").local_maps, maps)


def test_clearly_negative_variance_in_float32_statistics_fails(tmp_path, run):
    t, m = _first_map_frame(run)
    maps = _float32_accumulated(run.local_maps, 2000)
    # variance -0.25 m^2: n sum z^2 = 4.5e6 < (sum z)^2 = 5.0625e6, 6% of the scale (the
    # float32 tolerance there is 8 n eps = 0.14%)
    maps[m, 40, 41] = [1500.0, 2250.0, 3000.0]
    with pytest.raises(RunError, match=rf"bad\.npz: field 'local_maps': negative variance .* "
                                       rf"local map {m} \(frame {t}\), cell \(40, 41\) "
                                       rf"\(1 cells in all\)"):
        load_run(_save(tmp_path, run, local_maps=maps))
    maps[m, 40, 41] = [4.0, 2.0, 0.5]
    with pytest.raises(RunError, match=r"negative variance"):
        load_run(_save(tmp_path, run, local_maps=maps))


def test_float64_statistics_keep_their_tolerance(tmp_path, run):
    """A deficit of 5e-6 relative is beyond float64 rounding (but within float32's at n = 7)."""
    t, m = _first_map_frame(run)
    maps = run.local_maps.copy()
    maps[m, 2, 3] = [7, 0.7, 0.07 * (1 - 1e-5)]
    with pytest.raises(RunError, match=rf"negative variance .* local map {m} \(frame {t}\), "
                                       rf"cell \(2, 3\)"):
        load_run(_save(tmp_path, run, local_maps=maps))


@pytest.mark.parametrize("dtype", [np.int64, np.uint8, np.int32])
def test_integer_vo_failed_flags_load_as_bool(tmp_path, run, dtype):
    """Files that store the flags as integers 0/1 loaded before the dtype check."""
    flags = np.zeros(run.num_frames, dtype)
    flags[[2, 7]] = 1
    back = load_run(_save(tmp_path, run, vo_failed=flags))
    assert back.vo_failed.dtype == bool
    np.testing.assert_array_equal(back.vo_failed, flags.astype(bool))


def test_other_integer_vo_failed_flags_name_the_frame(tmp_path, run):
    flags = np.zeros(run.num_frames, np.int64)
    flags[[5, 9]] = [2, -1]
    with pytest.raises(RunError, match=r"bad\.npz: field 'vo_failed': expected bool or integers "
                                       r"0/1, got 2 at frame 5 \(2 frames in all\)"):
        load_run(_save(tmp_path, run, vo_failed=flags))


def test_size_one_resolution_array_loads_as_a_scalar(tmp_path, run):
    back = load_run(_save(tmp_path, run, resolution=np.array([run.resolution])))
    assert isinstance(back.resolution, float) and back.resolution == run.resolution
    back = load_run(_save(tmp_path, run, resolution=np.array([[run.resolution]], np.float32)))
    assert back.resolution == pytest.approx(run.resolution)


def test_string_fields(tmp_path, run):
    with pytest.raises(RunError, match=r"bad\.npz: field 'controls': expected real numbers, got dtype <U"):
        load_run(_save(tmp_path, run, controls=np.full(run.controls.shape, "fast")))
    with pytest.raises(RunError, match=r"bad\.npz: field 'controls': expected real numbers"):
        load_run(_save(tmp_path, run, controls=run.controls.astype(str)))  # would parse as floats
    with pytest.raises(RunError, match=r"bad\.npz: field 'resolution': expected real numbers"):
        load_run(_save(tmp_path, run, resolution=np.array("0.16")))


def test_validate_run_checks_in_memory_runs_too(run):
    with pytest.raises(RunError, match=r"<run>: field 'controls': expected real numbers"):
        validate_run(run._replace(controls=[["a", "b", "c"]] * run.num_frames))
    with pytest.raises(RunError, match=r"<run>: field 'timestamps': not increasing at frame 1"):
        validate_run(run._replace(timestamps=np.zeros(run.num_frames)))
    with pytest.raises(RunError, match=r"<run>: field 'resolution': expected a scalar"):
        validate_run(run._replace(resolution=np.array([0.16, 0.16])))


def test_nan_ground_truth_rows_mean_frames_without_ground_truth(tmp_path, run):
    gt = run.ground_truth.copy()
    gt[3:6] = np.nan
    gt[9, 2] = np.nan
    save_run(tmp_path / "gt.npz", run._replace(ground_truth=gt))
    back = load_run(tmp_path / "gt.npz")
    np.testing.assert_array_equal(back.ground_truth, gt)
    assert isinstance(back, Run)


@pytest.mark.parametrize("step", [0.16 / 256, 0.1 / 256, 1e-4, 0.05, 3.0])
def test_float32_limit_against_numpy_spacing(step):
    """Below the limit float32 numbers are at most ``step`` apart, at it they are not."""
    limit = float32_limit(step)
    below = np.nextafter(np.float32(limit), np.float32(0))
    assert np.spacing(below) <= step < np.spacing(np.float32(limit))


def test_far_initial_pose_is_refused(tmp_path, run):
    """Before: a start at (1e15, 1e15) ran, and float32 held one position for every frame."""
    far = np.array([1e15, 1e15, 0.0])
    in32 = integrate_controls(run.controls, far).astype(np.float32)
    assert len(np.unique(in32[:, :2], axis=0)) == 1  # the path the filter would have seen
    with pytest.raises(RunError, match=r"bad\.npz: field 'initial_pose': position \(1e\+15, "
                                       r"1e\+15\) m .* \(at most 8192 m from the origin"):
        load_run(_save(tmp_path, run, initial_pose=far))
    with pytest.raises(RunError, match=r"field 'initial_pose': heading 1e\+06 rad"):
        load_run(_save(tmp_path, run, initial_pose=np.array([0.0, 0.0, 1e6])))


def test_initial_pose_within_the_limit_loads_and_float32_follows_the_path(tmp_path, run):
    """Just inside the limit float32 still follows the float64 path to a small part of a cell."""
    limit = coordinate_limit(run.resolution)
    near = np.array([0.99 * limit, -0.99 * limit, 2.0])
    back = load_run(_save(tmp_path, run, initial_pose=near))
    np.testing.assert_array_equal(back.initial_pose, near)
    pose = near.astype(np.float32)
    for dx, dy, dth in run.controls.astype(np.float32):  # eq. 1 composed in float32
        c, s = np.cos(pose[2]), np.sin(pose[2])
        pose = pose + np.array([c * dx - s * dy, s * dx + c * dy, dth], np.float32)
    exact = integrate_controls(run.controls, near)[-1]
    assert np.abs(pose[:2] - exact[:2]).max() < 0.1 * run.resolution


def test_control_turning_more_than_pi_names_frame_and_value(tmp_path, run):
    """Before: a turn of 1e6 rad in one frame was accepted (2.7 m RMS against VO's 0.32 m)."""
    u = run.controls.copy()
    u[7, 2] = 1e6
    with pytest.raises(RunError, match=r"bad\.npz: field 'controls': frame 7 turns 1e\+06 rad"):
        load_run(_save(tmp_path, run, controls=u))
    u[7, 2] = -np.pi  # the largest turn a frame can express: still accepted
    load_run(_save(tmp_path, run, controls=u))


@pytest.mark.parametrize("frame", [0, 4])
def test_control_moving_absurdly_far_names_frame(tmp_path, run, frame):
    u = run.controls.copy()
    u[frame, 0] = 1e6  # a million metres in 0.2 s
    with pytest.raises(RunError, match=rf"field 'controls': frame {frame} moves 1e\+06 m in "
                                       r"0\.2 s \(5e\+06 m/s"):
        load_run(_save(tmp_path, run, controls=u))
    u[frame, 0] = 0.99 * MAX_SPEED * 0.2  # fast, but within the bound
    load_run(_save(tmp_path, run, controls=u))


def test_map_extent_beyond_float32_reach():
    """The VO path itself too far names the frame; a margin that takes the map there names
    [map] margin."""
    xy = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [9000.0, 5.0, 0.0]])
    def check(path, margin):
        check_float32_reach(path, map_extent(path, 128, 0.16, margin, 128), 0.16, margin)

    with pytest.raises(RunError, match=r"field 'controls': the VO path reaches \(9000, 5\) m "
                                       r"at frame 2"):
        check(xy, 5.0)
    with pytest.raises(ConfigError, match=r"\[map\] margin 10000 m"):
        check(xy[:2], 1e4)
    check(xy[:2], 5.0)


def test_prior_map_start_beyond_float32_reach_is_refused():
    """``gslam run --prior-map M --start 1e300,1e300,0`` passed as finite; now named."""
    from gslam_jax.config import Config
    from gslam_jax.driver.map_reuse import PriorMap, check_prior
    from gslam_jax.gridmap import GridMap

    grid = GridMap(np.ones((8, 8)), np.ones((8, 8)), (0.0, 0.0), 0.16)
    prior = PriorMap(grid, np.array([1e300, 1e300, 0.0]), np.zeros(3), "m.npz")
    with pytest.raises(ConfigError, match=r"--start \(the start pose in the prior map\): "
                                          r"position \(1e\+300, 1e\+300\) m"):
        check_prior(prior, Config())
    check_prior(prior._replace(start=np.array([100.0, -50.0, 3.0])), Config())


@pytest.mark.parametrize("x", [0.0, 1e-40, 1e-3, 1.0, 1.5, 8191.9, 8192.0, 1e15, 3e38, 1e300])
def test_float32_spacing_against_numpy(x):
    with np.errstate(over="ignore"):
        expected = float(np.spacing(np.float32(x)))
    assert float32_spacing(x) == (np.inf if np.isnan(expected) else expected)
