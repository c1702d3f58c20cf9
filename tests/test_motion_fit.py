"""Fitting the motion model's alphas (eqs. 2-3) to VO errors, and `gslam fit-motion`."""

import numpy as np
import pytest
from cached_runs import shared_run

from gslam_jax.app.cli import main
from gslam_jax.config import load_config
from gslam_jax.run import Run, integrate_controls, load_run, save_run
from gslam_jax.tuning.motion_fit import (ALPHA_THETA_MAX, MIN_STEP, MIN_TURN, MOVING_FRACTION,
                                         MotionFitError, _windows, fallback_scale, fit_motion,
                                         fit_run, update_interval)

KITTI_LIKE = (0.005, 0.0007, 0.01)


def simulate(alphas, n=10_000, seed=0, turn_std=0.2, alpha_cross=0.0):
    """VO controls u [n, 3] drawn by eqs. 1-3 around true increments (plus cross-track noise
    of std alpha_cross |d|), and the true poses; the stds scale with the true |d| and
    |dtheta|, as ``fit_motion`` regresses them (numpy)."""
    rng = np.random.default_rng(seed)
    dist = rng.uniform(0.1, 1.5, n)
    side = rng.normal(0.0, 0.1, n)  # direction of travel off the robot's x axis
    turn = rng.normal(0.0, turn_std, n)
    true_u = np.column_stack([dist * np.cos(side), dist * np.sin(side), turn])
    alpha_d, alpha_theta_d, alpha_theta = alphas
    scale = 1.0 + alpha_d * rng.standard_normal(n)  # eq. 2: along Delta d only
    sigma_theta = alpha_theta_d * dist + alpha_theta * np.abs(turn)  # eq. 3
    normal = np.column_stack([-true_u[:, 1], true_u[:, 0]])  # Delta d turned by +90 degrees
    cross = alpha_cross * rng.standard_normal(n) if alpha_cross else np.zeros(n)
    u = np.column_stack([true_u[:, :2] * scale[:, None] + normal * cross[:, None],
                         turn + sigma_theta * rng.standard_normal(n)])
    u[0] = true_u[0] = 0.0
    return u, integrate_controls(true_u, np.array([3.0, -1.0, 0.4]))


def moving_frames(ref, usable=None):
    """Frames t >= 1 whose true step is at least MOVING_FRACTION of the median step and
    MIN_STEP, or whose true turn is at least MIN_TURN."""
    diff = np.diff(ref, axis=0)
    step, turn = np.hypot(diff[:, 0], diff[:, 1]), np.abs(np.angle(np.exp(1j * diff[:, 2])))
    ok = np.isfinite(step) if usable is None else np.isfinite(step) & usable[1:]
    least = max(MOVING_FRACTION * np.median(step[ok]), MIN_STEP)
    return int(np.sum(ok & ((step >= least) | (turn >= MIN_TURN))))


@pytest.mark.parametrize("alphas", [(0.05, 0.01, 0.05), KITTI_LIKE])
def test_recovers_the_alphas(alphas):
    u, ref = simulate(alphas)
    fit = fit_motion(u, ref)
    assert fit.frames == moving_frames(ref) > 0.9 * len(u) and fit.window == 1
    # about 3 standard errors at n = 10000: 1% for alpha_d, 2% for the heading pair
    assert fit.alpha_d == pytest.approx(alphas[0], rel=0.03)
    assert fit.alpha_theta_d == pytest.approx(alphas[1], rel=0.06)
    assert fit.alpha_theta == pytest.approx(alphas[2], rel=0.06)
    assert fit.across_rms < 1e-9 and fit.alpha_cross < 1e-9  # eq. 1: none across the track
    dist = np.hypot(*np.diff(ref[:, :2], axis=0).T)
    dist = dist[dist >= MOVING_FRACTION * np.median(dist)]
    assert fit.along_rms == pytest.approx(alphas[0] * np.sqrt(np.mean(dist ** 2)), rel=0.03)
    assert not fit.alpha_theta_at_bound


@pytest.mark.parametrize("alpha_cross", [0.004, 0.01])  # VO-sized: errors of first order
def test_recovers_the_cross_track_noise(alpha_cross):
    """The cross-track constant (rbpf.motion) from errors across the true translation, beside
    unchanged along-track and heading fits."""
    u, ref = simulate(KITTI_LIKE, seed=3, alpha_cross=alpha_cross)
    fit = fit_motion(u, ref)
    assert fit.alpha_cross == pytest.approx(alpha_cross, rel=0.03)
    assert fit.alpha_d == pytest.approx(KITTI_LIKE[0], rel=0.03)
    assert fit.alpha_theta_d == pytest.approx(KITTI_LIKE[1], rel=0.06)


@pytest.mark.parametrize("turn_std", [0.0, 1e-9])
def test_alpha_theta_stays_bounded_without_turns(turn_std):
    u, ref = simulate((0.05, 0.01, 0.05), turn_std=turn_std)
    fit = fit_motion(u, ref)
    assert 0.0 <= fit.alpha_theta <= ALPHA_THETA_MAX and np.isfinite(fit.alpha_theta)
    assert fit.alpha_theta_d == pytest.approx(0.01, rel=0.03)  # the distance term carries it all


def test_failures_missing_truth_and_standing_still_are_not_used():
    u, ref = simulate(KITTI_LIKE, n=3000)
    failed, unknown, still = np.array([5, 40, 41, 900]), np.array([100, 2000]), np.array([7, 300])
    unknown_frames = np.concatenate([unknown, unknown + 1])  # a frame needs poses t-1 and t
    usable = np.ones(len(u), bool)
    usable[np.concatenate([failed, unknown_frames, still])] = False
    expected = fit_motion(u, ref, usable)
    bad_u, bad_ref = u.copy(), ref.copy()
    bad_u[failed] += [3.0, -2.0, 1.0]  # absurd errors, on frames that must not count
    bad_u[unknown_frames] += [3.0, -2.0, 1.0]
    bad_u[still, :2] = 0.0
    bad_u[still, 2] += 1.0
    bad_ref[unknown] = np.nan
    vo_failed = np.zeros(len(u), bool)
    vo_failed[failed] = True
    fit = fit_motion(bad_u, bad_ref, ~vo_failed)
    assert fit.frames == expected.frames == moving_frames(ref, usable)
    np.testing.assert_allclose(fit, expected, rtol=1e-9)
    assert fit.alpha_d < 0.01 and fit.heading_rms < 0.01


def test_turns_in_place_do_not_inflate_alpha_d():
    """A frame that turns on the spot (true |d| ~ 0) has no along-track error in eq. 2; its VO
    jitter must not be divided by its tiny step (rendered Mars Yard A: alpha_d 0.28 that way)."""
    u, ref = simulate(KITTI_LIKE, n=3000)
    steps = np.diff(ref, axis=0)
    spots = np.arange(10, 3000, 100)
    true_u = np.vstack([np.zeros(3), np.column_stack([
        np.cos(ref[:-1, 2]) * steps[:, 0] + np.sin(ref[:-1, 2]) * steps[:, 1],
        -np.sin(ref[:-1, 2]) * steps[:, 0] + np.cos(ref[:-1, 2]) * steps[:, 1],
        np.angle(np.exp(1j * steps[:, 2]))])])
    true_u[spots] = [1e-5, 0.0, 0.1]  # turn in place
    u[spots] = [1e-3, 0.0, 0.1]  # VO: 1 mm of jitter, 100 x the step
    ref = integrate_controls(true_u, ref[0])
    fit = fit_motion(u, ref)
    assert fit.alpha_d == pytest.approx(KITTI_LIKE[0], rel=0.1)
    assert fit.frames == moving_frames(ref)  # the turns in place fit the heading terms


def test_windows_are_consecutive_frames_and_gaps_break_them():
    frames = np.array([1, 2, 3, 4, 5, 7, 8, 9, 12, 13])
    np.testing.assert_array_equal(_windows(frames, 2), [[0, 1], [2, 3], [5, 6], [8, 9]])
    np.testing.assert_array_equal(_windows(frames, 3), [[0, 1, 2], [5, 6, 7]])


def test_windows_keep_independent_errors_and_widen_for_correlated_ones():
    """Independent errors: a 5-frame window fits the same alphas. A slowly varying heading bias
    (AR(1), correlation 0.9): the window's fit grows towards the spread the bias builds up."""
    u, ref = simulate(KITTI_LIKE, n=20_000, seed=4)
    one, five = fit_motion(u, ref), fit_motion(u, ref, window=5)
    assert five.window == 5
    assert five.alpha_d == pytest.approx(one.alpha_d, rel=0.06)
    assert five.alpha_theta_d == pytest.approx(one.alpha_theta_d, rel=0.15)
    rng = np.random.default_rng(5)
    bias_std, rho = 5e-3, 0.9
    bias = np.zeros(len(u))
    for t in range(1, len(u)):
        bias[t] = rho * bias[t - 1] + np.sqrt(1 - rho ** 2) * bias_std * rng.standard_normal()
    u_biased = u.copy()
    u_biased[1:, 2] += bias[1:]
    b_one, b_five = fit_motion(u_biased, ref), fit_motion(u_biased, ref, window=5)
    assert b_five.heading_rms == pytest.approx(b_one.heading_rms)  # same frames, per frame
    # the 5-frame sums of the heading errors, straight from the poses (every frame moves here)
    diff = np.diff(ref, axis=0)
    err = np.angle(np.exp(1j * (u_biased[1:, 2] - diff[:, 2])))
    n = len(err) // 5 * 5
    sums_rms = np.sqrt(np.mean(err[:n].reshape(-1, 5).sum(axis=1) ** 2))
    assert sums_rms > 1.7 * np.sqrt(5) * b_one.heading_rms  # the bias adds up
    dist, turn = np.hypot(diff[:n, 0], diff[:n, 1]), np.abs(diff[:n, 2])

    def window_std(fit):  # RMS over the windows of eq. 3's std of a 5-frame sum
        per_frame = fit.alpha_theta_d * dist + fit.alpha_theta * turn
        return np.sqrt(np.mean(np.sum(per_frame.reshape(-1, 5) ** 2, axis=1)))

    assert window_std(b_five) == pytest.approx(sums_rms, rel=0.1)
    assert window_std(b_one) < 0.9 * sums_rms  # the per-frame fit is too narrow there


def test_update_interval_is_the_median_spacing_of_the_local_maps():
    run = shared_run(40)  # _noisy_run_file's Run, built once
    obs = -np.ones(40, np.int32)
    obs[[0, 4, 8, 11, 15, 19]] = np.arange(6)
    assert update_interval(run._replace(obs_index=obs)) == 4
    assert update_interval(run._replace(obs_index=-np.ones(40, np.int32))) == 1


def test_too_few_frames_or_no_ground_truth_are_named_errors():
    u, ref = simulate(KITTI_LIKE, n=20)
    ref[4:] = np.nan  # frames 1-3 have both poses
    with pytest.raises(MotionFitError, match="3 usable frames of 20.*at least 5"):
        fit_motion(u, ref)
    with pytest.raises(MotionFitError, match="no ground truth"):
        fit_motion(u, None)
    with pytest.raises(MotionFitError, match="no ground truth"):
        fit_motion(u, np.full_like(ref, np.nan))
    with pytest.raises(MotionFitError, match=r"expected shape \(20, 3\)"):
        fit_motion(u, ref[:10])


def _noisy_run_file(tmp_path, steps=40):
    run = shared_run(steps)
    rng = np.random.default_rng(3)
    noise = rng.normal(0.0, [0.01, 0.002, 0.003], run.controls.shape)
    path = tmp_path / "r.npz"
    save_run(path, run._replace(controls=run.controls + noise))
    return path


@pytest.mark.slow
def test_cli_writes_a_config_with_the_fitted_motion(tmp_path, capsys):
    path = _noisy_run_file(tmp_path)
    out = tmp_path / "fitted.toml"
    assert main(["fit-motion", str(path), "--set", "filter.particles=8", "--out", str(out)]) == 0
    fit = fit_run(load_run(path))
    config = load_config(out)
    assert (config.motion.alpha_d, config.motion.alpha_theta_d, config.motion.alpha_theta,
            config.motion.alpha_cross) == (fit.alpha_d, fit.alpha_theta_d, fit.alpha_theta,
                                           fit.alpha_cross)
    assert config.filter.particles == 8  # the rest of the config is the one given
    text = capsys.readouterr().out
    assert "[motion]" in text and f"alpha_d = {fit.alpha_d!r}" in text
    assert f"frames used: {fit.frames} of 40" in text
    assert main(["fit-motion", str(path), "--out", str(out)]) == 2  # no --overwrite
    assert "exists" in capsys.readouterr().err
    assert main(["fit-motion", str(path), "--out", str(out), "--overwrite"]) == 0


def test_cli_without_ground_truth_exits_2(tmp_path, capsys):
    save_run(tmp_path / "r.npz", shared_run(40)._replace(ground_truth=None))
    assert main(["fit-motion", str(tmp_path / "r.npz")]) == 2
    assert "no ground truth" in capsys.readouterr().err


@pytest.mark.slow
def test_run_reports_the_fit_and_notes_motion_noise_far_off_it(tmp_path, capsys):
    import json

    path = _noisy_run_file(tmp_path)
    fit = fit_run(load_run(path))
    fitted = [f"motion.alpha_d={fit.alpha_d}", f"motion.alpha_theta_d={fit.alpha_theta_d}",
              f"motion.alpha_theta={fit.alpha_theta}"]
    for scale, noted in ((1.0, False), (20.0, True), (0.1, True)):
        out = tmp_path / f"out{scale}"
        sets = fitted[:1] + [f"motion.alpha_theta_d={fit.alpha_theta_d * scale}",
                             f"motion.alpha_theta={fit.alpha_theta * scale}"]
        args = ["run", str(path), "--out", str(out), "--set", "filter.particles=8"]
        assert main(args + [a for s in sets for a in ("--set", s)]) == 0
        summary = json.loads((out / "summary.json").read_text())["motion_fit"]
        assert summary["alpha_d"] == pytest.approx(fit.alpha_d)
        assert summary["configured_over_fitted_heading"] == pytest.approx(scale, rel=1e-6)
        assert ("note: the [motion] noise" in capsys.readouterr().out) == noted


@pytest.mark.parametrize("along, heading, sensor, side", [
    (8.1, 10.7, "stereo", None),       # KITTI's defaults: its best measured
    (1.0, 1.0, "stereo", "under 3x"),  # the fit itself: no better than VO-only there
    (16.0, 21.0, "stereo", "over 15x"),
    (1.0, 1.0, "points", None),        # the simulator: the fit does as well as the calibration
    (0.2, 1.0, "points", "under 0.33x"),
    (12.0, 45.0, "points", "over 10x"),
])
def test_the_motion_noise_note_follows_the_sensors_measured_range(along, heading, sensor, side):
    from gslam_jax.app.outputs import motion_noise_note

    fit = {"alpha_d": 0.006, "alpha_theta_d": 0.001, "alpha_theta": 0.0,
           "configured_over_fitted_along": along, "configured_over_fitted_heading": heading}
    note = motion_noise_note(fit, sensor)
    if side is None:
        assert note is None
    else:
        assert f"{along:.2g}x (along-track)" in note and f"lost accuracy {side}" in note
        assert f"On {sensor} local maps" in note


def test_a_vehicle_standing_still_is_refused_naming_how_many_frames_moved():
    """Ground truth that jitters by a fraction of a millimetre (a parked vehicle) fits no
    motion noise: every frame is under MIN_STEP, whatever the median step."""
    rng = np.random.default_rng(5)
    ref = np.cumsum(rng.normal(0.0, [1.5e-4, 1.5e-4, 1e-4], (200, 3)), axis=0)
    u = np.diff(ref, axis=0, prepend=ref[:1]) + rng.normal(0.0, 1e-4, (200, 3))
    with pytest.raises(MotionFitError, match=r"0 of 199 frames moved at least 0\.005 m"):
        fit_motion(u, ref)


def _run_with_fallback(scale: float, n: int = 6000, every: int = 5) -> Run:
    """Every ``every``-th frame's control from odometry ``scale`` times as noisy as the VO's:
    the same draws (same seed) with every alpha times ``scale``, so its errors are exactly
    ``scale`` times the VO's would have been there."""
    alphas = (0.05, 0.01, 0.05)
    u_vo, ref = simulate(alphas, n=n)
    u_fallback, _ = simulate(tuple(scale * a for a in alphas), n=n)
    failed = np.arange(n) % every == 2
    return Run(controls=np.where(failed[:, None], u_fallback, u_vo),
               obs_index=np.full(n, -1), local_maps=np.zeros((0, 4, 4, 3)), resolution=0.16,
               timestamps=np.arange(n) * 0.1, ground_truth=ref, vo_failed=failed)


@pytest.mark.parametrize("scale", [1.0, 3.0])
def test_fallback_scale_is_how_much_noisier_the_fallback_frames_are(scale):
    run = _run_with_fallback(scale)
    fit = fit_run(run, 1)  # the VO's frames alone: the fallback's do not widen the alphas
    assert fit.alpha_d == pytest.approx(0.05, rel=0.04)
    # 1200 fallback frames: the mean of their 2400 squared z has a standard error of 3 %
    assert fallback_scale(run, fit) == pytest.approx(scale, rel=0.05)


def test_fallback_scale_needs_fallback_frames_with_ground_truth():
    run = _run_with_fallback(3.0)
    fit = fit_run(run, 1)
    assert fallback_scale(run._replace(vo_failed=None), fit) is None
    few = np.zeros(run.num_frames, bool)
    few[[10, 20, 30]] = True  # under MIN_FRAMES
    assert fallback_scale(run._replace(vo_failed=few), fit) is None
    truth = run.ground_truth.copy()
    truth[run.vo_failed] = np.nan  # no fallback frame has ground truth at both ends
    assert fallback_scale(run._replace(ground_truth=truth), fit) is None


def test_cli_writes_the_fitted_fallback_scale(tmp_path, capsys):
    run = _run_with_fallback(3.0, n=2000)
    path = tmp_path / "fallback.npz"
    save_run(path, run)
    out = tmp_path / "fitted.toml"
    assert main(["fit-motion", str(path), "--window", "1", "--out", str(out)]) == 0
    want = fallback_scale(run, fit_run(run, 1))
    assert load_config(out).motion.fallback_scale == pytest.approx(want)
    assert 2.5 < want < 3.5
    assert f"errors {want:.3g}x the VO's" in capsys.readouterr().out
