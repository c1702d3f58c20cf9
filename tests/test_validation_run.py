"""Run files that used to load (or crash later with a traceback): each is a RunError naming the
file, the field and, where it applies, the first bad frame."""

import numpy as np
import pytest
from synthetic import make_run

from gslam_jax.run import Run, RunError, load_run, save_run, validate_run


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


def test_non_boolean_vo_failed(tmp_path, run):
    flags = np.zeros(run.num_frames)
    flags[2] = 0.5
    with pytest.raises(RunError, match=r"bad\.npz: field 'vo_failed': expected bool, got dtype float64"):
        load_run(_save(tmp_path, run, vo_failed=flags))


@pytest.mark.parametrize("value", [np.array([0.16, 0.16]), np.array([0.16])])
def test_non_scalar_resolution(tmp_path, run, value):
    with pytest.raises(RunError, match=r"bad\.npz: field 'resolution': expected a scalar"):
        load_run(_save(tmp_path, run, resolution=value))


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
    assert isinstance(back, Run) and "NaN rows" in validate_run.__doc__
