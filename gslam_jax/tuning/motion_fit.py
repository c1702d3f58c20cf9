"""Fit the motion model's noise constants (paper 5.1, eqs. 1-3) to VO errors on a log with
ground truth, by maximum likelihood.

Eq. 1 moves a pose by the VO increment u_t = (dx, dy, dtheta) (robot frame of t-1) with noise
q_d along Delta d and q_theta on the heading; eq. 2: std(q_d) = alpha_d |Delta d|; eq. 3:
std(q_theta) = alpha_theta_d |Delta d| + alpha_theta |Delta theta|. The errors of the VO
increments against the ground-truth increments are samples of (q_d, q_theta), so

- alpha_d has the closed form sqrt(mean((e_a / |d|)^2)), e_a the along-track error, and the
  cross-track constant alpha_cross (``rbpf.motion``; the paper has none) the same form in the
  cross-track error e_c;
- (alpha_theta_d, alpha_theta) minimise the Gaussian negative log-likelihood of the heading
  errors, both >= 0 and alpha_theta <= ``ALPHA_THETA_MAX`` (it is not identifiable when every
  |dtheta| is tiny, and must not run off then).

Only frames that moved at least ``MOVING_FRACTION`` of the median step, and at least
``MIN_STEP`` (a vehicle standing still moves only by its ground truth's jitter), fit alpha_d:
eq. 2 gives a turn in place (|d| ~ 0) no along-track error, and its e_a / |d| would be
arbitrarily large.
The heading fit also uses the frames that turned at least ``MIN_TURN`` (eq. 3's turn term is
what covers a turn in place); a robot standing still fits nothing.

The stds are regressed on the true |Delta d| and |Delta theta|, not the VO's: the VO's own
|Delta theta| contains its error, so on a nearly straight log the frames with large heading
errors are the frames with large VO turns, and the fit would blame the turning (alpha_theta)
for noise that turning does not cause (KITTI, 51 frames: alpha_theta 0.45 that way, against
true turns of 0.7 mrad per frame). Where turns and steps are large against the errors, as on
the logs the filter runs, the two agree.

NumPy and SciPy only (no JAX).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy import optimize

from gslam_jax.errors import InputError
from gslam_jax.run import Run
from gslam_jax.vo.geometry import increments_2d

__all__ = ["MotionFitError", "MotionFit", "IncrementErrors", "increment_errors", "fit_motion",
           "fit_run", "update_interval", "noise_ratios", "fallback_scale", "MIN_FRAMES",
           "MOVING_FRACTION", "MIN_STEP", "MIN_TURN", "ALPHA_THETA_MAX"]

MIN_FRAMES = 5
MOVING_FRACTION = 0.25  # frames fitting alpha_d moved at least this times the median step
MIN_STEP = 0.005  # m: ... and at least this far (a standing vehicle's jitter is not a step)
MIN_TURN = 0.01  # rad: a frame that moved less but turned this much still fits eq. 3
ALPHA_THETA_MAX = 1.0  # rad of heading noise std per rad turned: a bound, never a fit
_STD_FLOOR = 1e-12  # rad, keeps the heading std positive at alpha_theta_d = alpha_theta = 0


class MotionFitError(InputError):
    """The controls and ground truth cannot be fitted (no ground truth, too few frames, ...)."""


class MotionFit(NamedTuple):
    """The fitted constants of eqs. 2-3 and the error figures of the frames they came from."""

    alpha_d: float
    alpha_theta_d: float
    alpha_theta: float
    alpha_cross: float  # cross-track std per metre (rbpf.motion; the paper's eq. 1 has none)
    frames: int  # frames used (alpha_d: those that moved; heading: also those that turned)
    window: int  # consecutive frames whose summed errors were fitted (1: each frame alone)
    along_rms: float  # m, VO minus truth along the VO direction
    across_rms: float  # m, across it (the paper's eq. 1 assumes none)
    heading_rms: float  # rad
    median_dist: float  # m, median true |Delta d| of the frames used
    median_turn: float  # rad, median true |Delta theta|
    alpha_theta_at_bound: bool  # alpha_theta stopped at ALPHA_THETA_MAX (not identifiable)


class IncrementErrors(NamedTuple):
    """Per used frame: its number, the true increment's |d| and |dtheta| and the VO's errors
    against it."""

    frame: np.ndarray
    dist: np.ndarray
    turn: np.ndarray
    along: np.ndarray
    across: np.ndarray
    heading: np.ndarray


def _wrap(angle: np.ndarray) -> np.ndarray:
    return np.angle(np.exp(1j * angle))


def _used_frames(controls: np.ndarray, truth: np.ndarray, usable: np.ndarray | None) -> np.ndarray:
    """Frames t >= 1 with both poses known, not a VO failure and |d| > 0."""
    used = np.isfinite(truth).all(axis=1) & (np.hypot(controls[:, 0], controls[:, 1]) > 0)
    used[0] = False
    if usable is not None:
        used &= usable
    return used


def _check_inputs(controls: np.ndarray, reference: np.ndarray | None,
                  usable: np.ndarray | None) -> None:
    if controls.ndim != 2 or controls.shape[1] != 3:
        raise MotionFitError(f"controls: expected shape [T, 3], got {controls.shape}")
    if reference is None or not np.isfinite(reference).all(axis=-1).any():
        raise MotionFitError("no ground truth: fitting the motion model needs a log whose "
                             "reference poses are known (a Run with ground_truth)")
    if reference.shape != controls.shape:
        raise MotionFitError(f"ground truth: expected shape {controls.shape} (one pose per "
                             f"control), got {reference.shape}")
    if usable is not None and usable.shape != controls.shape[:1]:
        raise MotionFitError(f"usable: expected shape [{controls.shape[0]}], got {usable.shape}")


def increment_errors(controls: np.ndarray, reference: np.ndarray | None,
                     usable: np.ndarray | None = None) -> IncrementErrors:
    """VO minus ground-truth increments, split along/across the VO direction, on the usable
    frames (see ``fit_motion``); raises MotionFitError when fewer than MIN_FRAMES remain."""
    controls = np.asarray(controls, np.float64)
    reference = None if reference is None else np.asarray(reference, np.float64)
    usable = None if usable is None else np.asarray(usable, bool)
    _check_inputs(controls, reference, usable)
    with np.errstate(invalid="ignore"):  # NaN poses give NaN increments, which are not used
        truth = increments_2d(reference)
    used = _used_frames(controls, truth, usable)
    if used.sum() < MIN_FRAMES:
        raise MotionFitError(f"{int(used.sum())} usable frames of {len(controls)}: fitting the "
                             f"motion model needs at least {MIN_FRAMES} (frames after the first "
                             "with ground truth at both ends, no VO failure and |d| > 0)")
    u, g = controls[used], truth[used]
    dist = np.hypot(u[:, 0], u[:, 1])
    ux, uy = u[:, 0] / dist, u[:, 1] / dist
    ex, ey = u[:, 0] - g[:, 0], u[:, 1] - g[:, 1]
    return IncrementErrors(frame=np.flatnonzero(used), dist=np.hypot(g[:, 0], g[:, 1]),
                           turn=np.abs(g[:, 2]), along=ex * ux + ey * uy,
                           across=ey * ux - ex * uy, heading=_wrap(u[:, 2] - g[:, 2]))


def _heading_nll(x: np.ndarray, scale: np.ndarray, dist: np.ndarray, turn: np.ndarray,
                 err2: np.ndarray) -> tuple[float, np.ndarray]:
    """Mean Gaussian NLL (less log sqrt(2 pi)) of the windows' summed heading errors and its
    gradient in x, with (alpha_theta_d, alpha_theta) = x * scale; dist, turn [W, k]: a
    window's std is the root sum of squares of its frames' eq. 3 stds."""
    a, b = x * scale
    per_frame = a * dist + b * turn
    std = np.sqrt(np.sum(per_frame ** 2, axis=1)) + _STD_FLOOR
    nll = np.mean(np.log(std) + 0.5 * err2 / std ** 2)
    d_std = (1.0 / std - err2 / std ** 3) / len(std)  # d nll / d std
    grad = np.array([d_std @ (np.sum(per_frame * dist, axis=1) / std),
                     d_std @ (np.sum(per_frame * turn, axis=1) / std)])
    return float(nll), grad * scale


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def _windows(frames: np.ndarray, size: int) -> np.ndarray:
    """[W, size] positions in ``frames`` (sorted frame numbers) of runs of ``size`` consecutive
    frames: each stretch without a gap is cut into whole windows from its start."""
    breaks = np.flatnonzero(np.diff(frames) != 1) + 1
    out = [run[: len(run) // size * size].reshape(-1, size)
           for run in np.split(np.arange(len(frames)), breaks)]
    return np.concatenate(out) if out else np.zeros((0, size), int)


def _fit_heading(dist: np.ndarray, turn: np.ndarray, err: np.ndarray,
                 a_scale: float) -> tuple[float, float]:
    """ML (alpha_theta_d, alpha_theta) of eq. 3, bounded to [0, inf) x [0, ALPHA_THETA_MAX],
    from windows' (dist, turn [W, k]) summed heading errors ``err`` [W].

    Optimised in units of ``a_scale`` (the b = 0 closed form over the frames that moved) and of
    rms(e)/rms(|dtheta|), from b = 0 and from a mix; the first start wins ties, so an
    unidentifiable alpha_theta stays 0."""
    if a_scale == 0.0:
        return 0.0, 0.0
    turn_rms = _rms(np.sqrt(np.sum(turn ** 2, axis=1)))
    b_scale = min(_rms(err) / turn_rms, ALPHA_THETA_MAX) if turn_rms > 0 else ALPHA_THETA_MAX
    scale = np.array([a_scale, b_scale])
    args = (scale, dist, turn, err ** 2)
    bounds = [(0.0, None), (0.0, ALPHA_THETA_MAX / b_scale)]
    best = None
    for start in ([1.0, 0.0], [0.5, 0.5]):
        res = optimize.minimize(_heading_nll, np.array(start), args=args, jac=True,
                                method="L-BFGS-B", bounds=bounds)
        if best is None or res.fun < best.fun:
            best = res
    a, b = best.x * scale
    return float(a), float(min(b, ALPHA_THETA_MAX))


def _least_step(e: IncrementErrors) -> float:
    """The smallest true step (m) of a frame that fits alpha_d: ``MOVING_FRACTION`` of the
    median step, at least ``MIN_STEP``."""
    return max(MOVING_FRACTION * float(np.median(e.dist)), MIN_STEP)


def _fitting_frames(e: IncrementErrors, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Masks of the frames that fit the along-track noise (moved at least ``step``) and the
    heading noise (moved, or turned at least ``MIN_TURN``: eq. 3's turn term)."""
    moving = e.dist >= step
    return moving, moving | (e.turn >= MIN_TURN)


def fit_motion(controls: np.ndarray, reference: np.ndarray | None,
               usable: np.ndarray | None = None, window: int = 1) -> MotionFit:
    """Maximum-likelihood alphas of eqs. 2-3 from VO controls and ground-truth poses.

    controls [T, 3]: a Run's increments (controls[t] moves frame t-1 to t in the robot frame of
    t-1). reference [T, 3]: true poses (x, y, theta), NaN rows unknown. usable [T] bool: False
    marks frames not to use (VO failures). Frames t >= 1 with both poses known, usable and
    |d| > 0 are used; the truth increments are ``increments_2d(reference)``.

    window: fit the errors summed over runs of this many consecutive frames, whose variance
    under eqs. 2-3 is the sum of the frames' (independent) variances. VO errors are correlated
    from frame to frame (a slowly varying bias: KITTI's heading errors have a lag-1
    correlation of 0.89), so they grow faster than the independent model says; fitting over the
    frames between two map updates matches the spread the filter's weights meet.
    """
    if window < 1:
        raise MotionFitError(f"window must be at least 1 frame, got {window}")
    e = increment_errors(controls, reference, usable)
    step = _least_step(e)
    moving, heading = _fitting_frames(e, step)
    if moving.sum() < MIN_FRAMES:
        raise MotionFitError(f"{int(moving.sum())} of {len(e.dist)} frames moved at least "
                             f"{step:.3g} m (the larger of {MOVING_FRACTION} of the median step, "
                             f"{float(np.median(e.dist)):.3g} m, and {MIN_STEP} m): fitting the "
                             f"motion model needs at least {MIN_FRAMES} moving frames (a log "
                             "where the vehicle stands still fits nothing)")
    along_w = _windows(e.frame[moving], window)
    head_w = _windows(e.frame[heading], window)
    if len(along_w) < MIN_FRAMES or len(head_w) < MIN_FRAMES:
        raise MotionFitError(f"{min(len(along_w), len(head_w))} windows of {window} consecutive "
                             f"usable frames: fitting the motion model needs at least "
                             f"{MIN_FRAMES} (a smaller window, or a longer log)")
    dist, along = e.dist[moving][along_w], e.along[moving][along_w].sum(axis=1)
    across = e.across[moving][along_w].sum(axis=1)
    alpha_d = float(np.sqrt(np.mean(along ** 2 / np.sum(dist ** 2, axis=1))))
    alpha_cross = float(np.sqrt(np.mean(across ** 2 / np.sum(dist ** 2, axis=1))))
    h_dist, h_turn = e.dist[heading][head_w], e.turn[heading][head_w]
    h_err = e.heading[heading][head_w].sum(axis=1)
    a_scale = float(np.sqrt(np.mean(h_err ** 2 / np.sum(h_dist ** 2, axis=1))))
    alpha_theta_d, alpha_theta = _fit_heading(h_dist, h_turn, h_err, a_scale)
    return MotionFit(alpha_d=alpha_d, alpha_theta_d=alpha_theta_d, alpha_theta=alpha_theta,
                     alpha_cross=alpha_cross, frames=int(heading.sum()), window=window,
                     along_rms=_rms(e.along[moving]),
                     across_rms=_rms(e.across[moving]), heading_rms=_rms(e.heading[heading]),
                     median_dist=float(np.median(e.dist[moving])),
                     median_turn=float(np.median(e.turn[heading])),
                     alpha_theta_at_bound=alpha_theta >= ALPHA_THETA_MAX * (1 - 1e-9))


def noise_ratios(alphas: tuple[float, float, float], fit: MotionFit) -> tuple[float, float]:
    """How wide the motion noise ``alphas`` (alpha_d, alpha_theta_d, alpha_theta) is against
    ``fit``: the ratios of the along-track and heading stds (eqs. 2-3) at the fit's median step
    and turn (inf where the fit found no error)."""
    def ratio(mine: float, fitted: float) -> float:
        return mine / fitted if fitted > 0 else float("inf")

    def heading_std(alpha_theta_d: float, alpha_theta: float) -> float:  # eq. 3
        return alpha_theta_d * fit.median_dist + alpha_theta * fit.median_turn

    return (ratio(alphas[0], fit.alpha_d),
            ratio(heading_std(alphas[1], alphas[2]), heading_std(fit.alpha_theta_d,
                                                                 fit.alpha_theta)))


def update_interval(run: Run) -> int:
    """Median number of frames between the Run's local maps (the filter's updates); 1 without
    two of them."""
    updates = np.flatnonzero(np.asarray(run.obs_index) >= 0)
    return max(1, int(round(float(np.median(np.diff(updates)))))) if len(updates) > 1 else 1


def fit_run(run: Run, window: int | None = None) -> MotionFit:
    """``fit_motion`` on a Run: its controls and ground truth, without its VO-failure frames;
    ``window`` None: the Run's ``update_interval``."""
    usable = None if run.vo_failed is None else ~np.asarray(run.vo_failed, bool)
    return fit_motion(run.controls, run.ground_truth, usable,
                      update_interval(run) if window is None else window)


def _normalised_squares(e: IncrementErrors, fit: MotionFit, step: float) -> np.ndarray:
    """Each frame's errors over the stds ``fit`` gives them (eqs. 2-3), squared: along-track on
    the frames that moved at least ``step``, heading on those that moved or turned."""
    moving, heading = _fitting_frames(e, step)
    sd_along = fit.alpha_d * e.dist[moving]
    sd_heading = fit.alpha_theta_d * e.dist[heading] + fit.alpha_theta * e.turn[heading]
    z = [e.along[moving][sd_along > 0] / sd_along[sd_along > 0],
         e.heading[heading][sd_heading > 0] / sd_heading[sd_heading > 0]]
    return np.concatenate(z) ** 2


def fallback_scale(run: Run, fit: MotionFit) -> float | None:
    """``[motion] fallback_scale`` from the ground truth: how much wider the errors of the
    fallback odometry's frames (``Run.vo_failed``) are than the VO's, against the same fitted
    stds (eqs. 2-3 with ``fit``'s alphas, frame by frame): sqrt(mean z_fallback^2 / mean
    z_VO^2), z an along-track or heading error over its std. A ratio of two frame-level
    figures, so the window ``fit`` summed its errors over cancels. None when the Run has fewer
    than ``MIN_FRAMES`` fallback frames with ground truth that moved or turned."""
    if run.vo_failed is None or not np.any(run.vo_failed):
        return None
    failed = np.asarray(run.vo_failed, bool)
    try:
        e_fallback = increment_errors(run.controls, run.ground_truth, failed)
    except MotionFitError:
        return None
    e_vo = increment_errors(run.controls, run.ground_truth, ~failed)
    step = _least_step(e_vo)
    z_fallback = _normalised_squares(e_fallback, fit, step)
    z_vo = _normalised_squares(e_vo, fit, step)
    if z_fallback.size < MIN_FRAMES or not np.mean(z_vo) > 0:
        return None
    return float(np.sqrt(np.mean(z_fallback) / np.mean(z_vo)))
