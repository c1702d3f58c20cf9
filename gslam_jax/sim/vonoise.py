"""Visual-odometry noise: ground-truth increments -> VO increments, with known true parameters.

Per frame, with the true robot-frame increment (dx, dy, dtheta) and d = |(dx, dy)|:

- white noise per the paper's motion model (eqs. 1-3): the translation is scaled by
  (1 + alpha_d eps_1), i.e. noise of std alpha_d d along the direction of travel and none across
  it; the rotation gets (alpha_theta_d d + alpha_theta |dtheta|) eps_2;
- slow correlated bias, as real VO drifts: a scale bias and a heading bias per metre, each an
  Ornstein-Uhlenbeck process over distance travelled (stationary std, correlation length);
- VO failures: bursts of frames whose increment comes from wheel odometry instead (flagged in
  ``vo_failed``): wheels over-report distance (slip) and their heading is noisier.

The generating parameters are returned with the draws so tuning can be checked against them.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

__all__ = ["VONoiseParams", "VONoiseDraw", "true_increments", "apply_vo_noise", "VO_PROFILES"]


@dataclass(frozen=True)
class VONoiseParams:
    """True VO error parameters of a simulated run (units: fractions, rad/m, rad/rad)."""

    alpha_d: float = 0.02  # eq. 2: along-track std per metre travelled
    alpha_theta_d: float = 0.004  # eq. 3: heading std per metre travelled (rad/m)
    alpha_theta: float = 0.02  # eq. 3: heading std per radian turned
    scale_bias_std: float = 0.01  # stationary std of the scale bias (fraction)
    heading_bias_std: float = 0.002  # stationary std of the heading bias (rad/m)
    bias_length: float = 40.0  # correlation length of both biases (m of travel)
    failure_rate: float = 0.004  # probability per frame that a VO-failure burst starts
    failure_frames: tuple[int, int] = (2, 8)  # burst length range (frames)
    wheel_slip_mean: float = 0.04  # wheel odometry over-reports distance by this fraction
    wheel_slip_std: float = 0.04
    wheel_alpha_theta_d: float = 0.03
    wheel_alpha_theta: float = 0.08

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            if name != "failure_frames" and not (np.isfinite(value) and value >= 0):
                raise ValueError(f"VONoiseParams.{name} must be a finite value >= 0, got {value}")
        if self.bias_length <= 0:
            raise ValueError(f"VONoiseParams.bias_length must be positive, got {self.bias_length}")
        lo, hi = self.failure_frames
        if not 1 <= lo <= hi:
            raise ValueError(f"VONoiseParams.failure_frames must be 1 <= lo <= hi, got {lo, hi}")

    def scaled(self, factor: float) -> "VONoiseParams":
        """Same shape of noise, every std (white and bias) multiplied by ``factor``."""
        d = asdict(self)
        for name in ("alpha_d", "alpha_theta_d", "alpha_theta", "scale_bias_std",
                     "heading_bias_std"):
            d[name] *= factor
        return VONoiseParams(**d)


# Per-environment noise: VO was very good in the open arroyo field, worse in the maze (paper 7).
VO_PROFILES: dict[str, VONoiseParams] = {
    "mars-yard-a": VONoiseParams(heading_bias_std=0.0035),
    "mars-yard-b": VONoiseParams(heading_bias_std=0.0024),
    "arroyo-a": VONoiseParams(heading_bias_std=0.0003, scale_bias_std=0.004,
                              alpha_theta_d=0.0012, failure_rate=0.002),
    "arroyo-b": VONoiseParams(heading_bias_std=0.0004, alpha_theta_d=0.003),
    "maze": VONoiseParams(heading_bias_std=0.0011, alpha_theta_d=0.005, failure_rate=0.01),
}


@dataclass
class VONoiseDraw:
    """What was drawn: the biases per frame and the failure flags."""

    params: VONoiseParams
    scale_bias: np.ndarray  # [T]
    heading_bias: np.ndarray  # [T] rad/m
    vo_failed: np.ndarray  # [T] bool


def true_increments(poses: np.ndarray, initial_pose: np.ndarray | None = None) -> np.ndarray:
    """Robot-frame increments [T, 3] between consecutive world poses (first from ``initial_pose``,
    default: the first pose, so the first increment is zero)."""
    poses = np.asarray(poses, dtype=np.float64)
    prev = np.concatenate([[poses[0] if initial_pose is None else initial_pose], poses[:-1]])
    c, s = np.cos(prev[:, 2]), np.sin(prev[:, 2])
    dx, dy = poses[:, 0] - prev[:, 0], poses[:, 1] - prev[:, 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, poses[:, 2] - prev[:, 2]], axis=1)


def _ou(rng: np.random.Generator, dist: np.ndarray, std: float, length: float) -> np.ndarray:
    """Ornstein-Uhlenbeck process indexed by distance travelled, stationary std ``std``."""
    out = np.empty(dist.size)
    b = rng.normal(0.0, std)
    decay = np.exp(-dist / length)
    kick = std * np.sqrt(1.0 - decay * decay) * rng.normal(0.0, 1.0, dist.size)
    for t in range(dist.size):
        b = b * decay[t] + kick[t]
        out[t] = b
    return out


def _failures(rng: np.random.Generator, n: int, p: VONoiseParams,
              moving: np.ndarray) -> np.ndarray:
    failed = np.zeros(n, bool)
    starts = np.flatnonzero((rng.random(n) < p.failure_rate) & moving)
    for t in starts:
        failed[t:t + rng.integers(p.failure_frames[0], p.failure_frames[1] + 1)] = True
    failed[0] = False
    return failed


def apply_vo_noise(increments: np.ndarray, params: VONoiseParams,
                   rng: np.random.Generator) -> tuple[np.ndarray, VONoiseDraw]:
    """Noisy VO increments [T, 3] from true ones, and what was drawn (see module docstring)."""
    u = np.asarray(increments, dtype=np.float64)
    if u.ndim != 2 or u.shape[1] != 3:
        raise ValueError(f"increments must have shape [T, 3], got {u.shape}")
    p = params
    d = np.hypot(u[:, 0], u[:, 1])
    dth = np.abs(u[:, 2])
    scale_bias = _ou(rng, d, p.scale_bias_std, p.bias_length)
    heading_bias = _ou(rng, d, p.heading_bias_std, p.bias_length)
    eps = rng.normal(0.0, 1.0, (u.shape[0], 2))
    scale = 1.0 + scale_bias + p.alpha_d * eps[:, 0]
    rot = u[:, 2] + heading_bias * d + (p.alpha_theta_d * d + p.alpha_theta * dth) * eps[:, 1]
    # wheel odometry where VO failed: slip inflates distance; noisier heading
    failed = _failures(rng, u.shape[0], p, d > 1e-4)
    eps_w = rng.normal(0.0, 1.0, (u.shape[0], 2))
    w_scale = 1.0 + p.wheel_slip_mean + p.wheel_slip_std * eps_w[:, 0]
    w_rot = u[:, 2] + (p.wheel_alpha_theta_d * d + p.wheel_alpha_theta * dth) * eps_w[:, 1]
    scale = np.where(failed, w_scale, scale)
    rot = np.where(failed, w_rot, rot)
    out = np.stack([u[:, 0] * scale, u[:, 1] * scale, rot], axis=1)
    return out, VONoiseDraw(params=p, scale_bias=scale_bias, heading_bias=heading_bias,
                            vo_failed=failed)
