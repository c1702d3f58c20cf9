"""Simulated WAAS-like GPS receiver for ground-truth trajectories (paper appendix A.1).

The paper's receiver reports a horizontal EPE with typical errors of 3-10 m. Here the EPE is a
slow log-normal Gauss-Markov process clipped to [epe_min, epe_max] (sky visibility changes over
minutes), and the position error is a first-order Gauss-Markov process per axis whose stationary
std is EPE / sqrt(2), so the RMS horizontal error equals the reported EPE (its proportionality
assumption, A.1). Readings come at ``rate_hz`` in a GPS frame that is a rigid transform of the
simulator's world frame, and are also given as WGS84 lat/lon around a UTM site origin so they
can round-trip through a CSV log.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from gslam_jax.gps.log import GpsLog
from gslam_jax.gps.utm import utm_to_latlon

__all__ = ["GpsSimConfig", "SimulatedGps", "simulate_gps"]


class GpsSimConfig(NamedTuple):
    """Receiver and frame parameters (seconds, metres, radians).

    epe_median: median reported EPE; epe_log_std: std of log EPE; epe_tau: correlation time of
    the EPE; error_tau: correlation time of the position error (first-order Gauss-Markov);
    epe_report_noise: std of log(reported / true EPE) (receivers' EPE is only approximate);
    dropout: probability that a reading is missing; frame_rotation / frame_offset: the GPS
    (site) frame as x_gps = R(rot) x_world + offset; site_origin / zone / north: where the site
    frame sits in UTM (default: near the paper's Arroyo Seco site, zone 11N).
    """

    rate_hz: float = 1.0
    epe_median: float = 5.0
    epe_log_std: float = 0.3
    epe_min: float = 3.0
    epe_max: float = 10.0
    epe_tau: float = 120.0
    error_tau: float = 30.0
    epe_report_noise: float = 0.0
    dropout: float = 0.0
    frame_rotation: float = 0.0
    frame_offset: tuple[float, float] = (0.0, 0.0)
    site_origin: tuple[float, float] = (394000.0, 3783000.0)
    zone: int = 11
    north: bool = True


class SimulatedGps(NamedTuple):
    """log: readings as a GpsLog (site-frame xy, lat/lon, EPE); truth_xy [N,2]: the true
    positions in the same site frame; error_xy [N,2] = log.xy - truth_xy."""

    log: GpsLog
    truth_xy: np.ndarray
    error_xy: np.ndarray


def _gauss_markov(rng: np.random.Generator, n: int, dt: float, tau: float,
                  std: np.ndarray, dim: int) -> np.ndarray:
    """x_k = phi x_{k-1} + sqrt(1 - phi^2) std_k w_k, phi = exp(-dt / tau), x_0 ~ N(0, std_0^2)."""
    phi = np.exp(-dt / tau)
    w = rng.standard_normal((n, dim))
    x = np.empty((n, dim))
    x[0] = std[0] * w[0]
    q = np.sqrt(1.0 - phi**2)
    for k in range(1, n):
        x[k] = phi * x[k - 1] + q * std[k] * w[k]
    return x


def simulate_gps(rng: np.random.Generator, poses: np.ndarray, times: np.ndarray,
                 config: GpsSimConfig = GpsSimConfig()) -> SimulatedGps:
    """Simulate receiver readings for a ground-truth trajectory poses [T,3] at times [T].

    Readings start at times[0] and come every 1/rate_hz s; positions are linearly interpolated.
    Dropped readings are removed (``log.n_skipped`` counts them).
    """
    poses, times = np.asarray(poses, np.float64), np.asarray(times, np.float64)
    if poses.ndim != 2 or poses.shape[1] < 2 or poses.shape[0] != times.shape[0]:
        raise ValueError(f"poses must be [T,3] with times [T]; got {poses.shape}, {times.shape}")
    if poses.shape[0] < 2 or not np.all(np.diff(times) > 0):
        raise ValueError("need at least 2 poses with strictly increasing times")
    dt = 1.0 / config.rate_hz
    t = np.arange(times[0], times[-1] + 1e-9, dt)
    n = t.shape[0]
    world = np.stack([np.interp(t, times, poses[:, k]) for k in range(2)], -1)
    c, s = np.cos(config.frame_rotation), np.sin(config.frame_rotation)
    truth = world @ np.array([[c, -s], [s, c]]).T + np.asarray(config.frame_offset)

    log_epe = np.log(config.epe_median) + _gauss_markov(
        rng, n, dt, config.epe_tau, np.full(n, config.epe_log_std), 1)[:, 0]
    epe_true = np.clip(np.exp(log_epe), config.epe_min, config.epe_max)
    err = _gauss_markov(rng, n, dt, config.error_tau, epe_true / np.sqrt(2.0), 2)
    epe = epe_true * np.exp(config.epe_report_noise * rng.standard_normal(n))
    keep = rng.random(n) >= config.dropout

    xy = (truth + err)[keep]
    utm = xy + np.asarray(config.site_origin)
    lat, lon = utm_to_latlon(utm[:, 0], utm[:, 1], config.zone, config.north)
    log = GpsLog(t[keep], lat, lon, epe[keep], xy, np.asarray(config.site_origin, np.float64),
                 config.zone, config.north, int(n - keep.sum()))
    return SimulatedGps(log, truth[keep], err[keep])
