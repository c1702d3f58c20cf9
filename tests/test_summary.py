"""The run summary stays honest on degenerate runs: no drift percentage and no motion-noise
advice for a vehicle that hardly moved, and timing lines that say what they timed. (A run
that moved keeps its drift: tests/test_cli.py.)"""

import contextlib
import io
import json

import numpy as np
import pytest
from synthetic import World

from gslam_jax.app.cli import main
from gslam_jax.app.outputs import MIN_DRIFT_DISTANCE, timing_text
from gslam_jax.run import Run, integrate_controls, save_run
from gslam_jax.vo.localmap import LocalMapParams, build_local_maps


def _parked_run(moved: float, steps: int = 30, seed: int = 0) -> Run:
    """A vehicle creeping ``moved`` metres in a straight line, its VO jittering about it."""
    rng = np.random.default_rng(seed)
    step = moved / (steps - 1)
    u_true = np.tile([step, 0.0, 0.0], (steps, 1))
    u_true[0] = 0.0
    gt = integrate_controls(u_true)
    u_vo = u_true + rng.normal(0.0, [2e-3, 2e-3, 1e-3], (steps, 3))
    world = World(seed)
    frames = [world.observe(p, rng, n=4000) for p in gt]
    params = LocalMapParams(resolution=0.16, max_range=5.0, travel=0.05)
    obs_index, maps, *_ = build_local_maps(integrate_controls(u_vo), frames, params)
    return Run(controls=u_vo, obs_index=obs_index, local_maps=maps,
               resolution=params.resolution, timestamps=np.arange(steps) * 0.1,
               ground_truth=gt)


@pytest.fixture(scope="module")
def parked(tmp_path_factory):
    """`gslam run` on a vehicle that moved 0.3 m: its summary.json and console report."""
    tmp = tmp_path_factory.mktemp("parked")
    save_run(tmp / "r.npz", _parked_run(0.3))
    out = tmp / "out"
    text = io.StringIO()
    with contextlib.redirect_stdout(text):
        assert main(["run", str(tmp / "r.npz"), "--out", str(out),
                     "--set", "filter.particles=8"]) == 0
    print(text.getvalue())
    return json.loads((out / "summary.json").read_text()), text.getvalue()


def test_a_parked_vehicle_has_no_drift_percentage_and_says_why(parked):
    summary, printed = parked
    assert summary["gt_distance_m"] == pytest.approx(0.3, rel=1e-6)
    assert "vo_drift_pct" not in summary and "slam_drift_pct" not in summary
    assert "vo_rms_m" in summary  # the RMS is still a distance, still meaningful
    assert summary["drift_note"].startswith("the vehicle moved 0.3 m by the ground truth")
    assert "final drift" not in printed and "%" not in printed
    assert f"note: the vehicle moved 0.3 m by the ground truth, under {MIN_DRIFT_DISTANCE:g} m: " \
           "no drift percentage and no motion-noise check" in printed


def test_a_parked_vehicle_gets_no_motion_noise_advice(parked):
    summary, printed = parked
    assert "motion_fit" not in summary
    assert "note: the [motion] noise" not in printed and "fit-motion" not in printed


def test_the_timing_line_of_a_run_in_one_chunk_says_compilation_is_in_it(parked):
    summary, printed = parked
    assert summary["compile_frames"] == summary["frames"] == 30
    assert ("filter: " f"{summary['compile_seconds']:.1f} s for 30 frames, compilation "
            "included") in printed
    assert "filter time" not in printed and "first chunk incl." not in printed


def test_the_timing_line_of_a_longer_run_times_the_frames_after_the_first_chunk():
    line = timing_text({"frames": 2000, "compile_frames": 512, "compile_seconds": 6.04,
                        "filter_seconds": 2.976})
    # 1488 frames in 2.976 s: 2 ms a frame
    assert line == ("filter: 3.0 s for 1488 frames (2 ms a frame) after 6.0 s for compilation "
                    "and the first 512 frames")



def test_the_real_time_factor_is_log_time_over_compute(parked):
    summary, printed = parked
    assert summary["log_seconds"] == pytest.approx(2.9)  # 30 frames, 0.1 s apart
    compute = summary["filter_seconds"] + summary["compile_seconds"]
    assert summary["realtime_factor"] == pytest.approx(2.9 / compute)
    assert f"real-time factor {summary['realtime_factor']:.2g}: 2.9 s of log" in printed


def test_the_ess_target_is_reported_only_where_tempering_uses_it(parked, tmp_path):
    summary, _ = parked
    assert summary["tempering"] == "adaptive"
    assert summary["ess_target"] == 0.5  # automatic: the point sensor's (no sensor recorded)
    assert summary["proposal_draws"] == "independent"  # likewise
    assert summary["localmap_lattice"] == "robot"  # the Run has no lattice_headings
    save_run(tmp_path / "r.npz", _parked_run(0.3, steps=10))
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["run", str(tmp_path / "r.npz"), "--out", str(tmp_path / "o"),
                     "--set", "filter.particles=8", "--set", "filter.tempering=fixed"]) == 0
    fixed = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert fixed["tempering"] == "fixed" and fixed["ess_target"] is None
