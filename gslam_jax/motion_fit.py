"""Fit the motion model's noise constants (paper 5.1, eqs. 1-3) to VO errors on a log with
ground truth, by maximum likelihood.

Eq. 1 moves a pose by the VO increment u_t = (dx, dy, dtheta) (robot frame of t-1) with noise
q_d along Delta d and q_theta on the heading; eq. 2: std(q_d) = alpha_d |Delta d|; eq. 3:
std(q_theta) = alpha_theta_d |Delta d| + alpha_theta |Delta theta|. The errors of the VO
increments against the ground-truth increments are samples of (q_d, q_theta), so

- alpha_d has the closed form sqrt(mean((e_a / |d|)^2)), e_a the along-track error;
- (alpha_theta_d, alpha_theta) minimise the Gaussian negative log-likelihood of the heading
  errors, both >= 0 and alpha_theta <= ``ALPHA_THETA_MAX`` (it is not identifiable when every
  |dtheta| is tiny, and must not run off then).

Only frames that moved at least ``MOVING_FRACTION`` of the median step are used: eqs. 2-3 give
a standing robot no error, so a frame of a turn in place (|d| ~ 0) would make e_a / |d|
arbitrarily large. The stds are regressed on the true |Delta d| and |Delta theta|, not the
VO's: the VO's own |Delta theta| contains its error, so on a nearly straight log the frames with large heading
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
           "fit_run", "MIN_FRAMES", "MOVING_FRACTION", "ALPHA_THETA_MAX"]

MIN_FRAMES = 5
MOVING_FRACTION = 0.25  # frames fitting alpha_d moved at least this times the median step
ALPHA_THETA_MAX = 1.0  # rad of heading noise std per rad turned: a bound, never a fit
_STD_FLOOR = 1e-12  # rad, keeps the heading std positive at alpha_theta_d = alpha_theta = 0


class MotionFitError(InputError):
    """The controls and ground truth cannot be fitted (no ground truth, too few frames, ...)."""


class MotionFit(NamedTuple):
    """The fitted constants of eqs. 2-3 and the error figures of the frames they came from."""

    alpha_d: float
    alpha_theta_d: float
    alpha_theta: float
    frames: int  # frames used
    along_rms: float  # m, VO minus truth along the VO direction
    across_rms: float  # m, across it (eq. 1 assumes none)
    heading_rms: float  # rad
    median_dist: float  # m, median true |Delta d| of the frames used
    median_turn: float  # rad, median true |Delta theta|
    alpha_theta_at_bound: bool  # alpha_theta stopped at ALPHA_THETA_MAX (not identifiable)


class IncrementErrors(NamedTuple):
    """Per used frame: the true increment's |d| and |dtheta| and the VO's errors against it."""

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
    return IncrementErrors(dist=np.hypot(g[:, 0], g[:, 1]), turn=np.abs(g[:, 2]),
                           along=ex * ux + ey * uy,
                           across=ey * ux - ex * uy, heading=_wrap(u[:, 2] - g[:, 2]))


def _heading_nll(x: np.ndarray, scale: np.ndarray, basis: np.ndarray,
                 err2: np.ndarray) -> tuple[float, np.ndarray]:
    """Mean Gaussian NLL (less log sqrt(2 pi)) of the heading errors and its gradient in x,
    with (alpha_theta_d, alpha_theta) = x * scale and basis = [|d|, |dtheta|] columns."""
    std = basis @ (x * scale) + _STD_FLOOR
    nll = np.mean(np.log(std) + 0.5 * err2 / std ** 2)
    d_std = (1.0 / std - err2 / std ** 3) / len(std)
    return float(nll), (basis.T @ d_std) * scale


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def _fit_heading(dist: np.ndarray, turn: np.ndarray, err: np.ndarray) -> tuple[float, float]:
    """ML (alpha_theta_d, alpha_theta) of eq. 3, bounded to [0, inf) x [0, ALPHA_THETA_MAX].

    Optimised in units of the b = 0 closed form and of rms(e)/rms(|dtheta|), from b = 0 and
    from a mix; the first start wins ties, so an unidentifiable alpha_theta stays 0."""
    a_scale = _rms(err / dist)
    if a_scale == 0.0:
        return 0.0, 0.0
    turn_rms = _rms(turn)
    b_scale = min(_rms(err) / turn_rms, ALPHA_THETA_MAX) if turn_rms > 0 else ALPHA_THETA_MAX
    scale = np.array([a_scale, b_scale])
    args = (scale, np.column_stack([dist, turn]), err ** 2)
    bounds = [(0.0, None), (0.0, ALPHA_THETA_MAX / b_scale)]
    best = None
    for start in ([1.0, 0.0], [0.5, 0.5]):
        res = optimize.minimize(_heading_nll, np.array(start), args=args, jac=True,
                                method="L-BFGS-B", bounds=bounds)
        if best is None or res.fun < best.fun:
            best = res
    a, b = best.x * scale
    return float(a), float(min(b, ALPHA_THETA_MAX))


def fit_motion(controls: np.ndarray, reference: np.ndarray | None,
               usable: np.ndarray | None = None) -> MotionFit:
    """Maximum-likelihood alphas of eqs. 2-3 from VO controls and ground-truth poses.

    controls [T, 3]: a Run's increments (controls[t] moves frame t-1 to t in the robot frame of
    t-1). reference [T, 3]: true poses (x, y, theta), NaN rows unknown. usable [T] bool: False
    marks frames not to use (VO failures). Frames t >= 1 with both poses known, usable and
    |d| > 0 are used; the truth increments are ``increments_2d(reference)``.
    """
    e = increment_errors(controls, reference, usable)
    moving = e.dist >= MOVING_FRACTION * np.median(e.dist)
    if moving.sum() < MIN_FRAMES:
        raise MotionFitError(f"{int(moving.sum())} frames moved at least {MOVING_FRACTION} of "
                             f"the median step ({np.median(e.dist):.3g} m): fitting the motion "
                             f"model needs at least {MIN_FRAMES}")
    e = IncrementErrors(*(field[moving] for field in e))
    alpha_theta_d, alpha_theta = _fit_heading(e.dist, e.turn, e.heading)
    return MotionFit(alpha_d=_rms(e.along / e.dist), alpha_theta_d=alpha_theta_d,
                     alpha_theta=alpha_theta, frames=len(e.dist), along_rms=_rms(e.along),
                     across_rms=_rms(e.across), heading_rms=_rms(e.heading),
                     median_dist=float(np.median(e.dist)), median_turn=float(np.median(e.turn)),
                     alpha_theta_at_bound=alpha_theta >= ALPHA_THETA_MAX * (1 - 1e-9))


def fit_run(run: Run) -> MotionFit:
    """``fit_motion`` on a Run: its controls and ground truth, without its VO-failure frames."""
    usable = None if run.vo_failed is None else ~np.asarray(run.vo_failed, bool)
    return fit_motion(run.controls, run.ground_truth, usable)
