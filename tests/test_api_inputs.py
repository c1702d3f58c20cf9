"""The public Python API's bad inputs: each refused with the project's error naming the
argument and why, before any work, as the command line names an option.

Before, a NaN local map was pushed and reported ``updated=True`` (an inf one was refused),
negative counts likewise, and the rest raised NumPy's or Python's own errors (AttributeError,
TypeError, ValueError without the argument's name).
"""

from __future__ import annotations

import numpy as np
import pytest

import gslam_jax
from gslam_jax.config import Config
from gslam_jax.errors import ArgumentError, InputError


@pytest.fixture(scope="module")
def live():
    """An Online that never runs a frame: every push below is refused before the filter."""
    return gslam_jax.Online(Config(), 20.0)


def _map(live, cell=(3, 4), value=(np.nan, 0.0, 0.0)) -> np.ndarray:
    L = live.cfg.local_size
    stats = np.zeros((L, L, 3))
    stats[cell] = value
    return stats


@pytest.mark.parametrize("value, message", [
    ((np.nan, 0.0, 0.0), r"frame 0: local_map: non-finite statistics in cell \(3, 4\)"),
    ((1.0, np.nan, 1.0), r"frame 0: local_map: non-finite statistics in cell \(3, 4\)"),
    ((-2.0, 0.0, 0.0), r"frame 0: local_map: negative point count n in cell \(3, 4\)"),
    ((1.5, 1.0, 1.0), r"frame 0: local_map: non-integer point count n in cell \(3, 4\)"),
    ((2.0, 4.0, 1.0), r"frame 0: local_map: negative variance .* in cell \(3, 4\)"),
], ids=["nan-count", "nan-sum", "negative-count", "fractional-count", "negative-variance"])
def test_a_local_map_a_run_file_could_not_hold_is_refused(live, value, message):
    with pytest.raises(InputError, match=message):
        live.push([0.1, 0.0, 0.0], _map(live, value=value))
    assert live.frames == 0


BAD_PUSHES = [
    (lambda lv: lv.push("abc"), r"frame 0: control must be 3 finite numbers .* got 'abc'"),
    (lambda lv: lv.push([0.1, 0.0]), r"frame 0: control must be 3 finite numbers"),
    (lambda lv: lv.push([0.1, 0.0, 0.0], "abc"),
     r"frame 0: local_map must be \[\d+, \d+, 3\] statistics .* real numbers, got 'abc'"),
    (lambda lv: lv.push([0.1, 0.0, 0.0], None, "soon"), r"frame 0: time_s must be a finite "
     r"number, got 'soon'"),
    (lambda lv: lv.push([0.1, 0.0, 0.0], None, float("nan")), r"frame 0: time_s must be a "
     r"finite number"),
    (lambda lv: lv.push([0.1, 0.0, 0.0], None, None, "north"), r"frame 0: lattice_heading "
     r"must be a finite number"),
    (lambda lv: lv.push([0.1, 0.0, 0.0], None, None, 0.0, "yes"), r"frame 0: vo_failed must "
     r"be True or False"),
    (lambda lv: lv.push_points("abc", np.zeros((4, 3))), r"frame 0: control must be 3 finite "
     r"numbers"),
    (lambda lv: lv.push_points([0.1, 0.0, 0.0], np.zeros((4, 2))), r"frame 0: points must be "
     r"robot-frame points .*shape \[N, 3\], got shape \[4, 2\]"),
    (lambda lv: lv.push_points([0.1, 0.0, 0.0], np.zeros(3)), r"frame 0: points must be "
     r"robot-frame points .*shape \[N, 3\], got shape \[3\]"),
    (lambda lv: lv.push_points([0.1, 0.0, 0.0], [[1.0, 2.0, np.inf]]), r"frame 0: points must "
     r"be finite, got inf at index \(0, 2\)"),
    (lambda lv: lv.push_points([0.1, 0.0, 0.0], "abc"), r"frame 0: points must be robot-frame "
     r"points"),
]


@pytest.mark.parametrize("call, message", BAD_PUSHES, ids=range(len(BAD_PUSHES)))
def test_a_malformed_push_names_the_argument(live, call, message):
    with pytest.raises(ArgumentError, match=message):
        call(live)
    assert live.frames == 0


BAD_ONLINE = [
    (lambda: gslam_jax.Online({}, 20.0), r"Online: config must be a gslam_jax.Config .*got "
     r"dict"),
    (lambda: gslam_jax.Online(Config(), "big"), r"Online: map_extent must be a side in metres"),
    (lambda: gslam_jax.Online(Config(), ((0.0, 0.0), (64, 2.5))), r"Online: map_extent's "
     r"shape must be 2 positive integers, got 2.5"),
    (lambda: gslam_jax.Online(Config(), ((0.0,), (64, 64))), r"Online: map_extent must be"),
    (lambda: gslam_jax.Online(Config(), 20.0, seed=-1), r"Online: seed must be an integer in "
     r"\[0, 2\^32\), got -1"),
    (lambda: gslam_jax.Online(Config(), 20.0, seed=1.5), r"Online: seed must be an integer"),
    (lambda: gslam_jax.Online(Config(), 20.0, local_size=0), r"Online: local_size must be an "
     r"integer >= 1, got 0"),
    (lambda: gslam_jax.Online(Config(), 20.0, observed_cells=-1), r"Online: observed_cells "
     r"must be an integer >= 0 \(0: no cap\)"),
    (lambda: gslam_jax.Online(Config(), 20.0, sensor="lidar"), r"Online: sensor must be one "
     r"of"),
    (lambda: gslam_jax.Online(Config(), filter_config={}), r"Online: filter_config must be "
     r"an rbpf.FilterConfig"),
    (lambda: gslam_jax.Online(Config(), 20.0, start_pose="abc"), r"Online: start_pose must be "
     r"3 finite numbers"),
]


@pytest.mark.parametrize("call, message", BAD_ONLINE, ids=range(len(BAD_ONLINE)))
def test_online_names_a_bad_argument(call, message):
    with pytest.raises(InputError, match=message):
        call()


@pytest.mark.parametrize("args, kwargs, message", [
    (("mars-yard-a",), {"seed": -1}, r"simulate_run: seed must be an integer in \[0, 2\^32\), "
     r"got -1"),
    (("mars-yard-a",), {"seed": 1.5}, r"simulate_run: seed must be an integer .*got 1.5"),
    (("mars-yard-a",), {"seed": True}, r"simulate_run: seed must be an integer"),
    (("mars-yard-a",), {"noise_seed": 2 ** 32}, r"simulate_run: noise_seed must be an integer"),
    (("mars-yard-a",), {"max_frames": 2.5}, r"simulate_run: max_frames must be a positive "
     r"integer .*got 2.5"),
    (("mars-yard-a",), {"max_frames": 0}, r"simulate_run: max_frames must be a positive "
     r"integer"),
    (("nowhere",), {}, r"simulate_run: course must be one of mars-yard-a, .*got 'nowhere'"),
])
def test_simulate_run_names_a_bad_argument(args, kwargs, message):
    with pytest.raises(ArgumentError, match=message):
        gslam_jax.simulate_run(*args, **kwargs)


def test_run_slam_and_save_run_name_what_they_were_given(tmp_path):
    run, _ = gslam_jax.simulate_run("mars-yard-a", max_frames=3)
    with pytest.raises(ArgumentError, match=r"run_slam: run must be a gslam_jax.Run .*got dict"):
        gslam_jax.run_slam({}, Config())
    with pytest.raises(ArgumentError, match=r"run_slam: config must be a gslam_jax.Config"):
        gslam_jax.run_slam(run, {})
    with pytest.raises(ArgumentError, match=r"run_slam: chunk must be an integer >= 1"):
        gslam_jax.run_slam(run, Config(), chunk=0)
    with pytest.raises(InputError, match=r"x.npz: expected a gslam_jax.Run, got dict"):
        gslam_jax.save_run(tmp_path / "x.npz", {})
    assert list(tmp_path.iterdir()) == []
