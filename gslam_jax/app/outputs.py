"""The results of a run: trajectories, maps, figures, ``summary.json`` and the console report.

:func:`write_outputs` writes every file of ``gslam run`` into a staging folder
(``results.results_folder``); :func:`print_summary` prints the report of a finished run.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from gslam_jax.config import Config
from gslam_jax.datasets.registry import LoadedSource

if TYPE_CHECKING:
    from gslam_jax.driver.map_reuse import PriorMap
    from gslam_jax.driver.results import SlamResult

__all__ = ["json_ready", "write_figures", "local_maps_used", "summarise", "write_outputs",
           "print_summary", "timing_text", "MOTION_NOISE_RANGE", "MIN_DRIFT_DISTANCE"]

# Below this ground-truth distance (metres) a run has no drift percentage and no motion-noise
# check: a vehicle standing still turns any error into a huge percentage of almost nothing,
# and its VO errors are noise about no motion.
MIN_DRIFT_DISTANCE = 1.0


def json_ready(value):
    """``value`` with NumPy scalars as Python numbers and NaN/inf as None (valid JSON)."""
    if isinstance(value, dict):
        return {k: json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _write_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(json_ready(data), indent=2, allow_nan=False))


def write_figures(out: Path, run, result, num_particles: int,
                  threshold: float = 0.5) -> np.ndarray:
    """Map PNGs (VO-only beside Gamma-SLAM, coloured by expected std) and the ESS plot with the
    resampling threshold (``threshold`` J, filter.resample_ratio); with ground truth, the truth
    over the maps and ``errors.png`` (position error against distance travelled, after the
    RMS's rigid fit). Returns the Gamma-SLAM map's expected std."""
    from gslam_jax.app import plots
    from gslam_jax.evaluation import metrics
    from gslam_jax.gridmap import pose_maps
    from gslam_jax.rbpf import cells

    slam_std = np.asarray(cells.expected_std(result.kmap, result.smap))
    slam_at = (*result.map_origin, result.map_heading)  # the lattice may be turned
    vo_map = pose_maps.vo_only_map(run)
    vo_std = np.asarray(cells.expected_std(vo_map.k, vo_map.S))
    plots.save_map_png(out / "map.png", slam_std, slam_at, result.resolution,
                       path=result.path, title="Gamma-SLAM map (best particle)",
                       path_label="Gamma-SLAM path")
    plots.save_map_comparison_png(out / "maps_vo_vs_slam.png", vo_std, vo_map.origin, slam_std,
                                  slam_at, result.resolution, vo_path=result.vo_path,
                                  slam_path=result.path)
    plots.save_ess_png(out / "ess.png", result.ess, num_particles, resampled=result.resampled,
                       threshold=threshold)
    if run.ground_truth is not None:
        gt = metrics.ground_truth_in_map_frame(run.ground_truth, result.vo_path)
        if np.isfinite(gt).any():
            plots.save_ground_truth_png(out / "ground_truth.png", vo_std, vo_map.origin,
                                        slam_std, slam_at, result.resolution, gt,
                                        result.vo_path, result.path)
        if np.isfinite(np.asarray(run.ground_truth)[:, :2]).all(axis=1).sum() >= 2:
            plots.save_errors_png(out / "errors.png", run.ground_truth,
                                  [("VO only", result.vo_path), ("Gamma-SLAM", result.path)])
    return slam_std


def _write_utm_figure(out: Path, slam_std: np.ndarray, result) -> None:
    """``map_utm_figure.png``: the map resampled north-up in UTM (``geotiff.run_north_up``)
    with ``trajectory_utm.txt``'s path, as a figure with axes, legend and colour bar."""
    from gslam_jax.app import plots
    from gslam_jax.app.geotiff import NODATA, run_north_up

    north = run_north_up(out, slam_std, result.kmap, result.map_origin, result.resolution,
                         result.map_heading)
    std = np.where(north.bands[0] == NODATA, np.nan, north.bands[0])
    utm = np.loadtxt(out / "trajectory_utm.txt", ndmin=2)
    plots.save_utm_map_png(out / "map_utm_figure.png", std, north.transform, utm[:, 1:3],
                           crs=f"EPSG:{north.epsg}")


def local_maps_used(run) -> int:
    """How many of the Run's local maps the filter used: those some frame's ``obs_index``
    names (a local map no frame names never updates a particle)."""
    index = np.asarray(run.obs_index)
    return int(np.unique(index[index >= 0]).size)


def summarise(run, result, config: Config, description: str) -> dict:
    """The figures of ``summary.json`` (without the GPS figures). With ground truth that moved
    less than MIN_DRIFT_DISTANCE there is no drift percentage and no ``motion_fit``; a
    ``drift_note`` says why."""
    from gslam_jax.driver import sizing
    from gslam_jax.evaluation import metrics

    summary = {
        "source": description,
        "frames": run.num_frames,
        "local_maps": run.num_local_maps,
        "local_maps_used": local_maps_used(run),
        "distance_m": run.distance(),
        "particles": config.filter.particles,
        "estimate": config.filter.estimate,
        "sensor": run.sensor,
        "tempering": config.filter.tempering,
        # the adaptive exponent's target; fixed tempering (the paper's beta) has none
        "ess_target": (sizing.resolve_ess_target(config.filter.ess_target, run.sensor)
                       if config.filter.tempering == "adaptive" else None),
        "proposal_draws": sizing.resolve_proposal_draws(config.filter.proposal_draws,
                                                        run.sensor),
        # the axes the Run's local maps were binned on ([localmap] lattice, "auto" resolved when
        # they were built; a Run file keeps it as its lattice_headings)
        "localmap_lattice": "robot" if run.lattice_headings is None else "map",
        "resampling_events": int(np.sum(result.resampled)),
        "extent_violations": result.extent_violations,
        "empty_observations": result.empty_observations,
        "vo_failures": int(np.sum(run.vo_failed)) if run.vo_failed is not None else 0,
        # those frames' motion noise as a multiple of the VO's ([motion] fallback_scale)
        "fallback_scale": config.motion.fallback_scale,
        # each particle's own factor on the motion stds ([motion] noise_spread; 1: none) and
        # the surviving particles' at the end, their weighted geometric mean
        "noise_spread": config.motion.noise_spread,
        "final_noise_scale": (float(result.noise_scale[-1]) if config.motion.noise_spread > 1
                              and result.noise_scale is not None else None),
        "filter_seconds": result.seconds,
        "compile_seconds": result.compile_seconds,
        **_realtime(run, result),
        "compile_frames": result.compile_frames,
    }
    if run.ground_truth is not None:
        paths = {"vo": result.vo_path, "slam": result.path}
        summary.update(metrics.errors_over_known_frames(paths, run.ground_truth))
        drift = metrics.drift_over_known_frames(paths, run.ground_truth)
        moved = drift.get("gt_distance_m")
        if moved is not None and moved < MIN_DRIFT_DISTANCE:
            summary["gt_distance_m"] = moved
            summary["drift_note"] = (
                f"the vehicle moved {moved:.1f} m by the ground truth, under "
                f"{MIN_DRIFT_DISTANCE:g} m: no drift percentage and no motion-noise check")
        else:
            summary.update(drift)
            summary.update(_motion_check(run, config))
    return summary


def _motion_check(run, config: Config) -> dict:
    """``motion_fit``: the [motion] alphas fitted to this run's VO errors (``gslam fit-motion``)
    and how wide the configured noise is against them; empty when the run cannot be fitted."""
    from gslam_jax.tuning.motion_fit import MotionFitError, fit_run, noise_ratios

    try:
        fit = fit_run(run)
    except MotionFitError:
        return {}
    m = config.motion
    along, heading = noise_ratios((m.alpha_d, m.alpha_theta_d, m.alpha_theta), fit)
    return {"motion_fit": {"alpha_d": fit.alpha_d, "alpha_theta_d": fit.alpha_theta_d,
                           "alpha_theta": fit.alpha_theta, "alpha_cross": fit.alpha_cross,
                           "window_frames": fit.window,
                           "frames": fit.frames, "configured_over_fitted_along": along,
                           "configured_over_fitted_heading": heading}}


def write_outputs(out: Path, loaded: LoadedSource, result, config: Config,
                  gps_input=None, prior=None, consistency=None) -> dict:
    """Every output file of a run into ``out`` (a staging folder); returns the summary. With a
    ``prior`` map (``map_reuse.PriorMap``) the summary records it (``prior_summary``); with
    the map's check against itself (``consistency.Consistency``), that.

    The TUM files carry the dataset's own clock (``Run.time_origin_ns`` added, e.g. EuRoC's
    nanosecond timestamps); ``ground_truth_tum.txt`` holds the frames with a finite
    ground-truth pose, beside the estimate, for evo. ``trajectory_robot_kitti.txt`` is the path
    in KITTI's file layout and this project's robot frame; on KITTI runs
    (``loaded.kitti_frame``) ``trajectory_kitti.txt`` is the path in KITTI's camera frame, that
    of ``poses/NN.txt`` (``datasets.kitti.camera_poses``). With GPS, the georeferenced outputs
    (``georeference.write_gps_outputs``) and ``map_utm.tif`` (``geotiff``, when rasterio is
    installed). ``map_occupancy.pgm`` / ``.yaml``: the map for ROS ``map_server``
    (``occupancy``). ``summary.json`` is written last."""
    from gslam_jax.app.occupancy import write_occupancy
    from gslam_jax.config import config_to_toml
    from gslam_jax.io import save_map, write_kitti, write_tum

    run = loaded.run
    origin = run.time_origin_ns
    (out / "config.toml").write_text(config_to_toml(config))
    if loaded.sim_info is not None:
        (out / "simulation.json").write_text(json.dumps(loaded.sim_info.summary(), indent=2,
                                                        default=float))
    write_tum(out / "trajectory_tum.txt", run.timestamps, result.path, origin_ns=origin)
    write_kitti(out / "trajectory_robot_kitti.txt", result.path)
    if loaded.kitti_frame is not None:
        from gslam_jax.datasets.kitti import camera_poses
        cams = camera_poses(result.path, run.start_pose(), loaded.kitti_frame)
        np.savetxt(out / "trajectory_kitti.txt", cams[:, :3, :].reshape(-1, 12), fmt="%.9e")
    write_tum(out / "vo_tum.txt", run.timestamps, result.vo_path, origin_ns=origin)
    # the path of the particle whose map map.npz holds (the reported path is [filter] estimate's)
    write_tum(out / "map_path_tum.txt", run.timestamps, result.map_path, origin_ns=origin)
    if run.ground_truth is not None:
        gt = np.asarray(run.ground_truth, np.float64)
        known = np.isfinite(gt).all(axis=1)
        if known.any():
            write_tum(out / "ground_truth_tum.txt", np.asarray(run.timestamps)[known], gt[known],
                      origin_ns=origin)
    save_map(out / "map.npz", result.kmap, result.smap, result.map_origin, result.resolution,
             heading=result.map_heading)
    np.savez_compressed(out / "trace.npz", ess=result.ess, exponent=result.exponent,
                        resampled=result.resampled, **({} if result.noise_scale is None else
                                                       {"noise_scale": result.noise_scale}),
                        updated=result.updated, log_lik=result.log_lik,
                        best_pose=result.best_pose, mean_pose=result.mean_pose)
    summary = summarise(run, result, config, loaded.description)
    slam_std = write_figures(out, run, result, config.filter.particles,
                             config.filter.resample_ratio)
    write_occupancy(out, slam_std, (*result.map_origin, result.map_heading), result.resolution)
    if prior is not None:
        summary["prior_map"] = prior_summary(prior, result)
    if consistency is not None:
        summary["map_consistency"] = consistency.summary()
    if gps_input is not None:
        from gslam_jax.app.geotiff import write_run_geotiff
        from gslam_jax.gps import georeference
        summary["gps"] = georeference.write_gps_outputs(out, gps_input, run, result, slam_std)
        summary["gps"].update(write_run_geotiff(out, slam_std, result.kmap, result.map_origin,
                                                result.resolution, result.map_heading))
        _write_utm_figure(out, slam_std, result)
    _write_json(out / "summary.json", summary)
    return summary


# print_summary notes [motion] noise outside this range of the run's fitted noise (configured
# over fitted std, along-track and heading), by the run's sensor: the range in which the logs
# measured did well (docs/notebook/real-data.md, "How wide the motion noise").
MOTION_NOISE_RANGE = {"points": (1 / 3, 10.0), "stereo": (3.0, 15.0)}


def _realtime(run, result) -> dict:
    """``log_seconds`` (the run's time span) and ``realtime_factor``: seconds of log per
    second of filter compute, compilation included (what a robot's first run costs)."""
    t = np.asarray(run.timestamps, np.float64)
    span = float(t[-1] - t[0]) if t.size else 0.0
    compute = result.seconds + result.compile_seconds
    return {"log_seconds": span, "realtime_factor": span / compute if compute > 0 else None}


def timing_text(summary: dict) -> str:
    """The filter's time: the first chunk of frames (``compile_frames``) is timed together with
    the compilation, the rest (``filter_seconds``) without it."""
    frames, first = summary["frames"], summary["compile_frames"]
    compiled = f"{summary['compile_seconds']:.1f} s"
    if first >= frames:
        return (f"filter: {compiled} for {frames} frames, compilation included (all frames ran "
                "in the first chunk, which compiles)")
    rest, seconds = frames - first, summary["filter_seconds"]
    return (f"filter: {seconds:.1f} s for {rest} frames ({1e3 * seconds / rest:.3g} ms a frame) "
            f"after {compiled} for compilation and the first {first} frames")


def motion_noise_note(fit: dict, sensor: str) -> str | None:
    """What ``print_summary`` says about the [motion] noise against the run's fitted noise
    (``summary.json``'s ``motion_fit``), when it lies outside ``MOTION_NOISE_RANGE`` of the
    run's sensor; None inside it."""
    low, high = MOTION_NOISE_RANGE[sensor]
    off = {k: fit[f"configured_over_fitted_{k}"] for k in ("along", "heading")}
    if all(low <= r <= high for r in off.values()):
        return None
    side = f"under {low:.2g}x" if any(r < low for r in off.values()) else f"over {high:.2g}x"
    return (f"the [motion] noise is {off['along']:.2g}x (along-track) and {off['heading']:.2g}x "
            f"(heading) what this run's VO errors fit (alpha_d {fit['alpha_d']:.2g}, "
            f"alpha_theta_d {fit['alpha_theta_d']:.2g}, alpha_theta {fit['alpha_theta']:.2g}). "
            f"On {sensor} local maps the logs measured did well with {low:.2g}-{high:g}x them "
            f"and lost accuracy {side} (docs/notebook/real-data.md, \"How wide the motion noise\")")


def print_summary(summary: dict, run, result) -> None:
    """The console report of a finished run."""
    print(f"distance: {summary['distance_m']:.1f} m by VO")
    if run.ground_truth is not None:
        scored = summary["gt_frames_scored"]
        over = "" if scored == run.num_frames else \
            f" (over the {scored} of {run.num_frames} frames with ground truth)"
        if "vo_rms_m" in summary:
            print(f"VO-only RMS: {summary['vo_rms_m']:.3f} m{over}")
            print(f"Gamma-SLAM RMS: {summary['slam_rms_m']:.3f} m{over}")
        if "slam_drift_pct" in summary:
            print(f"ground-truth distance: {summary['gt_distance_m']:.1f} m, final drift: VO-only "
                  f"{summary['vo_drift_pct']:.2f} %, Gamma-SLAM {summary['slam_drift_pct']:.2f} %")
        elif "drift_note" in summary:
            print(f"note: {summary['drift_note']}")
        elif "vo_rms_m" not in summary:
            print(f"ground truth: only {scored} of {run.num_frames} frames have a finite pose; "
                  "no RMS")
    fit = summary.get("motion_fit")
    if fit is not None:
        note = motion_noise_note(fit, summary.get("sensor") or "points")
        if note:
            print(f"note: {note}")
    print(f"resampling events: {summary['resampling_events']}")
    if summary.get("final_noise_scale") is not None:
        print(f"motion noise: the particles' factor on the [motion] alphas ended at "
              f"{summary['final_noise_scale']:.3g} (weighted geometric mean; they started "
              f"spread over 1/{summary['noise_spread']:g}-{summary['noise_spread']:g})")
    print(timing_text(summary))
    if summary.get("realtime_factor") is not None:
        compute = summary["filter_seconds"] + summary["compile_seconds"]
        print(f"real-time factor {summary['realtime_factor']:.2g}: {summary['log_seconds']:.1f} s "
              f"of log in {compute:.1f} s of filter compute, compilation included")
    if result.extent_violations:
        print(f"WARNING: {result.extent_violations} particle updates reached the map edge")
    used, total = summary["local_maps_used"], summary["local_maps"]
    if total and not used:
        print(f"WARNING: no frame uses any of the Run's {total} local maps (obs_index is -1 "
              "everywhere): the filter made no map update; the path is dead reckoning")
    elif used < total:
        print(f"WARNING: only {used} of the Run's {total} local maps are used by a frame "
              "(obs_index); the others were ignored")
    if result.empty_observations:
        print(f"note: {result.empty_observations} local maps had no informative cell "
              "(weights unchanged)")
    if summary["vo_failures"]:
        print(f"note: {summary['vo_failures']} frames came from the fallback odometry (VO "
              f"failed), their motion noise {summary['fallback_scale']:g}x the VO's ([motion] "
              "fallback_scale)")


def prior_summary(prior: PriorMap, result: SlamResult) -> dict:
    """What ``summary.json`` records of a run on a prior map: where the map came from, the
    start pose and its spread, the prior's known cells and the cells the run added to it."""
    from gslam_jax.gridmap import place

    grid = place(prior.grid, result.map_origin, result.kmap.shape)
    known = np.asarray(result.kmap) > 0
    return {"path": prior.source, "start": np.asarray(prior.start, float).tolist(),
            "start_sigma": np.asarray(prior.start_sigma, float).tolist(),
            **({"start_located": prior.located} if prior.located is not None else {}),
            "origin": list(prior.grid.origin), "resolution": prior.grid.resolution,
            "prior_known_cells": int(grid.known.sum()),
            "cells_added": int(np.sum(known & ~grid.known)),
            "known_cells": int(known.sum())}
