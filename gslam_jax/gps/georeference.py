"""A finished run placed on the Earth: its GPS readings checked, aligned, written in UTM.

``gslam run --gps`` reads the log (or simulates one) and checks it against the run *before*
the filter runs (``gps_input``), then fits the reported path ([filter] estimate) to it and
writes the georeferenced outputs (``write_gps_outputs``; paper section 8 and appendix). The
fit (``gps.align``), the UTM conversion (``gps.utm``), the log format (``gps.log``) and the
world-file raster (``gps.raster``) live beside it; this module is the workflow around them.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from gslam_jax import gps
from gslam_jax.rbpf import cells
from gslam_jax.config import ConfigError
from gslam_jax.gps.log import GpsLog, GpsLogError
from gslam_jax.run import known_positions

__all__ = ["GpsInput", "gps_input", "write_gps_outputs", "outlier", "OUTLIER_EPE"]


class GpsInput(NamedTuple):
    """The readings of ``--gps``, checked against the run before the filter: name (file or
    "simulated GPS"), the log, true positions (simulated only) and the mask of readings inside
    the run's time span."""

    name: str
    log: GpsLog
    truth_xy: np.ndarray | None
    inside: np.ndarray


def gps_input(name: str, run, seed: int = 0, log: GpsLog | None = None) -> GpsInput:
    """The GPS readings for ``run``: ``log`` (read by ``gps.read_gps_log`` from the file
    ``name``) or, without one, a simulated WAAS-like receiver on the run's ground truth
    (``seed``).

    GPS times are seconds on the run's clock (``Run.timestamps``). Fewer than 2 readings
    inside the run's time span is a GpsLogError; fewer than half prints a warning.
    """
    truth_xy = None
    name = str(name)
    if log is None:
        if run.ground_truth is None:
            raise ConfigError("--gps sim needs a run with ground truth")
        from gslam_jax.gps.simulate import GpsSimConfig, simulate_gps
        gt = np.asarray(run.ground_truth, np.float64)
        known = known_positions(gt)
        if known.sum() < 2:
            raise ConfigError("--gps sim needs ground truth at 2 frames or more")
        sim = simulate_gps(np.random.default_rng(seed), gt[known],
                           np.asarray(run.timestamps)[known], GpsSimConfig())
        log, truth_xy, name = sim.log, sim.truth_xy, "simulated GPS"
    t = np.asarray(run.timestamps, np.float64)
    inside = gps.readings_in_span(t, log.time)
    n, n_in = len(log.time), int(inside.sum())
    span = f"run [{t[0]:.3f}, {t[-1]:.3f}] s, log [{log.time[0]:.3f}, {log.time[-1]:.3f}] s"
    if n_in < 2:
        raise GpsLogError(f"{name}: {n_in} of {n} GPS readings fall inside the run's time span, "
                          f"need at least 2 ({span}); GPS times must be seconds on the run's "
                          "clock (Run.timestamps)")
    usable = inside & np.isfinite(log.xy).all(axis=1)
    times = np.unique(np.asarray(log.time, np.float64)[usable])
    if len(times) < 2:
        raise GpsLogError(f"{name}: the {int(usable.sum())} usable GPS readings inside the run's "
                          f"time span are all at one time ({times[0] if len(times) else 'none'}"
                          " s); the alignment needs readings at 2 times or more")
    vo = run.vo_poses()[:, :2]
    at = np.stack([np.interp(times, t, vo[:, k]) for k in range(2)], -1)
    if np.ptp(at, axis=0).max() < 1e-3:
        raise GpsLogError(f"{name}: the run's VO path does not move between the GPS readings "
                          f"({times[0]:.3f} to {times[-1]:.3f} s on the run's clock); the "
                          "alignment's rotation would be undetermined")
    if n_in < 0.5 * n:
        print(f"WARNING: {name}: only {n_in} of {n} GPS readings fall inside the run's time span "
              f"({span}); the others are not used")
    return GpsInput(name, log, truth_xy, inside)


OUTLIER_EPE = 5.0  # residual (in EPEs, and in typical residuals) beyond which a reading is dropped


def outlier(resid: np.ndarray, epe: np.ndarray, used: np.ndarray) -> int | None:
    """Index of the reading to drop from the GPS fit, or None: the ``used`` reading with the
    largest residual in EPEs, u = resid / epe, when u exceeds OUTLIER_EPE times the larger of 1
    and the used readings' typical u (1.4826 times their median: a path that drifts widens
    every residual, and is not an outlier). At least 3 readings are always kept."""
    idx = np.flatnonzero(used)
    if len(idx) <= 3:
        return None
    u = resid[idx] / epe[idx]
    scale = max(1.0, 1.4826 * float(np.median(u)))
    worst = int(np.argmax(u))
    return int(idx[worst]) if u[worst] > OUTLIER_EPE * scale else None


def _describe(log: GpsLog, i: int, resid: float) -> str:
    where = f"line {int(log.lines[i])}, " if log.lines is not None else ""
    return (f"{where}time {log.time[i]:.3f} s, {resid:.1f} m off (EPE {log.epe[i]:.1f} m)")


def write_gps_outputs(out: Path, readings: GpsInput, run, result,
                      std: np.ndarray | None = None) -> dict:
    """Align the reported path of ``result`` (``SlamResult.path``) to the readings (weighted
    Procrustes, paper appendix) and write ``trajectory_utm.txt``, ``map_utm.png`` (+ world
    file) and ``gps_alignment.npz`` to ``out``; returns the summary's "gps" figures (readings
    used, residuals, map corners).
    ``std``: the map's expected std when the caller has it already (else computed here)."""
    log, truth_xy = readings.log, readings.truth_xy
    used = readings.inside & np.isfinite(log.xy).all(axis=1)
    t0 = float(run.timestamps[0])
    t, gt = np.asarray(run.timestamps, np.float64) - t0, np.asarray(log.time, np.float64) - t0
    keep = np.ones(len(log.time), bool)
    while True:  # the fit, less the worst outlier, until none is left (``outlier_limit``)
        try:
            al, aligned = gps.align_to_gps(run.timestamps, result.path[:, :2], log.time,
                                           log.xy, log.epe, keep)
        except ValueError as err:
            raise GpsLogError(f"{readings.name}: {err}") from err
        # residuals of the fit at the readings, in metres (float64 host interpolation)
        aligned = np.asarray(aligned, np.float64)
        at_gps = np.stack([np.interp(gt, t, aligned[:, k]) for k in range(2)], -1)
        resid = np.linalg.norm(at_gps - np.where(used[:, None], log.xy, 0.0), axis=1)
        worst = outlier(resid, log.epe, used & keep)
        if worst is None:
            break
        keep[worst] = False
    dropped = np.flatnonzero(used & ~keep)
    used = used & keep
    path_gps = np.asarray(gps.transform_poses(al, result.path), np.float64)
    path_gps[:, :2] += np.asarray(log.origin, np.float64)
    np.savetxt(out / "trajectory_utm.txt", np.column_stack([run.timestamps, path_gps]),
               fmt="%.4f", header=f"time easting northing heading (UTM zone {log.zone}"
               f"{'N' if log.north else 'S'}, EPSG:{log.epsg})")
    shape = result.kmap.shape
    # the map is read on its lattice's axes (``SlamResult.map_heading`` in the run's frame)
    R = gps.lattice_rotation(al.R, result.map_heading)
    corners = (gps.map_corners(result.map_origin, result.resolution, shape) @ R.T
               + np.asarray(al.l, np.float64) + log.origin)
    if std is None:
        std = np.asarray(cells.expected_std(result.kmap, result.smap))
    gps.write_georeferenced_png(out / "map_utm.png", std, result.map_origin, result.resolution,
                                R, al.l, log.origin, cmap="inferno")
    np.savez(out / "gps_alignment.npz", R=np.asarray(al.R), l=np.asarray(al.l),
             site_origin=np.asarray(log.origin), zone=log.zone, epsg=log.epsg,
             map_corners_utm=corners)
    n, n_used, cost = int(len(log.time)), int(al.n_used), float(al.cost)
    report = {"readings": n, "skipped": int(log.n_skipped),
              "inside_run": int(readings.inside.sum()), "used": n_used,
              "weighted_residual": cost,
              "residual_rms_m": float(np.sqrt(np.mean(resid[used] ** 2))),
              "epsg": log.epsg, "map_corners_utm": corners.tolist()}
    skipped = f", {report['skipped']} skipped by the reader" if report["skipped"] else ""
    outliers = f", {len(dropped)} dropped as outliers" if len(dropped) else ""
    print(f"GPS: {n_used} of {n} readings used ({n - report['inside_run']} outside the run's time "
          f"span{skipped}{outliers}); weighted residual {cost:.3g} ({cost / max(n_used, 1):.3g} "
          f"per reading), residual RMS {report['residual_rms_m']:.2f} m")
    if len(dropped):
        report["outliers"] = [
            {**({"line": int(log.lines[i])} if log.lines is not None else {}),
             "time": float(log.time[i]), "residual_m": float(resid[i]),
             "epe_m": float(log.epe[i])} for i in dropped]
        print(f"WARNING: {readings.name}: {len(dropped)} GPS reading(s) lie far beyond their EPE "
              f"from the fit of the others (residual over {OUTLIER_EPE:g} EPE and over "
              f"{OUTLIER_EPE:g} times the readings' typical residual) and were left out of the "
              "alignment: " + "; ".join(_describe(log, i, resid[i]) for i in dropped[:5])
              + (f"; and {len(dropped) - 5} more (summary.json's gps.outliers)"
                 if len(dropped) > 5 else ""))
    if truth_xy is not None:
        ok = used & np.isfinite(truth_xy).all(axis=1)
        err_slam = np.linalg.norm(at_gps[ok] - truth_xy[ok], axis=1)
        err_gps = np.linalg.norm(log.xy[ok] - truth_xy[ok], axis=1)
        report["raw_gps_rms_m"] = float(np.sqrt(np.mean(err_gps ** 2)))
        report["aligned_slam_rms_m"] = float(np.sqrt(np.mean(err_slam ** 2)))
        print(f"GPS: raw RMS {report['raw_gps_rms_m']:.2f} m, aligned Gamma-SLAM RMS in the GPS "
              f"frame {report['aligned_slam_rms_m']:.2f} m")
    return report
