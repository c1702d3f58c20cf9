"""The ``gslam run`` pipeline: a source -> Gamma-SLAM -> a complete results folder.

``cli`` parses arguments into a :class:`Source` and calls :func:`run_pipeline`; table1, the
experiments and the tests can call the same steps: :func:`load_source` (simulator, rendered
stereo, KITTI, EuRoC or a Run file), :func:`check_gps` (the GPS readings against the run,
before the filter), ``slam.run_slam``, then :func:`write_outputs` (trajectories, maps,
figures, summary, GPS outputs) into a folder from ``results.results_folder``, which becomes
the target only once every file is written.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import tempfile
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np

from gslam_jax.config import Config, ConfigError
from gslam_jax.app.results import ResultsError, results_folder

__all__ = ["Source", "LoadedSource", "check_source", "load_source", "check_save_run",
           "save_run_file", "check_local_map_size", "write_outputs", "print_summary",
           "run_pipeline", "json_ready", "MAX_LOCAL_CELLS"]

Progress = Callable[[int, int], None]
ProgressFactory = Callable[[str], Progress]

# Local maps wider than this many cells per side are refused before the source runs: the
# paper's 10 m range at 0.16 m needs 128; at 1024 one local map alone is 25 MB of statistics
# and every update scatters up to a million cells per particle.
MAX_LOCAL_CELLS = 1024


@dataclasses.dataclass(frozen=True)
class Source:
    """Where a run's frames come from: a Run file, or a simulated / recorded source.

    ``seed`` is the simulation seed (None: 0); it only applies to simulated sources and to
    ``--gps sim``. ``max_frames`` cuts simulated and dataset sources, not a Run file.
    """

    run_file: Path | None = None
    source: str = "sim"
    course: str = "mars-yard-a"
    path: Path | None = None
    sequence: str | None = None
    seed: int | None = None
    max_frames: int | None = None
    on_bad_frame: str = "error"

    @property
    def simulated(self) -> bool:
        return self.run_file is None and self.source in ("sim", "sim-stereo")

    @property
    def images(self) -> bool:
        """Frames come from stereo images through the OpenCV front-end."""
        return self.run_file is None and self.source in ("sim-stereo", "kitti", "euroc")


class LoadedSource(NamedTuple):
    run: object          # gslam_jax.run.Run
    description: str
    sim_info: object | None  # datasets.sim.SimInfo for the simulator


def check_source(src: Source, config: Config | None = None, gps: str | None = None) -> None:
    """ConfigError for source options that would be silently ignored: source options beside a
    Run file, --path/--sequence for another source, --seed where nothing is simulated, and
    [stereo] settings for a source without images."""
    if src.run_file is not None:
        extra = [opt for opt, given in (("--source", src.source != "sim"),
                                        ("--path", src.path is not None),
                                        ("--sequence", src.sequence is not None),
                                        ("--max-frames", src.max_frames is not None)) if given]
        if extra:
            raise ConfigError(f"{src.run_file}: a Run file is used as it is; {', '.join(extra)} "
                              "only apply without one (drop them, or re-create the Run with "
                              "--save-run)")
    else:
        if src.path is not None and src.source not in ("kitti", "euroc"):
            raise ConfigError(f"--path is for --source kitti/euroc, not --source {src.source}")
        if src.sequence is not None and src.source != "kitti":
            raise ConfigError(f"--sequence is for --source kitti, not --source {src.source}")
    if src.seed is not None and not src.simulated and str(gps) != "sim":
        what = str(src.run_file) if src.run_file is not None else f"--source {src.source}"
        raise ConfigError(f"--seed {src.seed}: {what} is not simulated, so the simulation seed "
                          "would be ignored; the filter's seed is filter.seed (--set "
                          "filter.seed=N)")
    if config is not None and not config.stereo.is_default() and not src.images:
        what = str(src.run_file) if src.run_file is not None else f"--source {src.source}"
        raise ConfigError(f"[stereo] settings apply to stereo images (--source sim-stereo, "
                          f"kitti, euroc); {what} has none")


def _stereo(config: Config, default):
    """The source's DenseStereoParams ``default`` with the config's [stereo] settings."""
    st = config.stereo
    changes = {k: v for k, v in (("num_disparities", st.num_disparities), ("block", st.block),
                                 ("stride", st.stride), ("algorithm", st.algorithm)) if v}
    return dataclasses.replace(default, **changes)


def check_local_map_size(config: Config) -> None:
    """ConfigError, before any source runs, when a local map would exceed MAX_LOCAL_CELLS
    cells per side ([localmap] max_range or cells against [map] resolution)."""
    from gslam_jax.slam import localmap_params

    L = localmap_params(config).size
    if L > MAX_LOCAL_CELLS:
        lm = config.localmap
        how = (f"[localmap] cells = {lm.cells}" if lm.cells else
               f"[localmap] max_range {lm.max_range:g} m at [map] resolution "
               f"{config.map.resolution:g} m")
        raise ConfigError(f"{how} gives local maps of {L} x {L} cells ({L * L * 24 / 2**20:.0f} "
                          f"MB of statistics each), more than {MAX_LOCAL_CELLS} per side; use a "
                          "coarser [map] resolution or a shorter [localmap] max_range")


def load_source(src: Source, config: Config, progress: Progress | None = None) -> LoadedSource:
    """The Run of ``src`` (after the front-end for image sources), its description and, for
    the simulator, its SimInfo. ``progress(done, total)`` follows the frames."""
    from gslam_jax.run import load_run
    from gslam_jax.slam import localmap_params

    params = localmap_params(config)
    seed = 0 if src.seed is None else src.seed
    if src.run_file is not None:
        return LoadedSource(load_run(src.run_file), str(src.run_file), None)
    if src.source == "sim":
        from gslam_jax.datasets.sim import simulate_run
        run, info = simulate_run(src.course, seed=seed, params=params,
                                 max_frames=src.max_frames, progress=progress)
        return LoadedSource(run, f"simulated course {src.course} (seed {seed})", info)
    if src.source == "sim-stereo":
        from gslam_jax.datasets.sim_stereo import SimStereoParams, load_sim_stereo
        sp = SimStereoParams()
        sp = dataclasses.replace(sp, frontend=dataclasses.replace(
            sp.frontend, stereo=_stereo(config, sp.frontend.stereo)))
        run, info = load_sim_stereo(src.course, seed, params, max_frames=src.max_frames,
                                    progress=progress, params=sp)
        print(info.text())
        return LoadedSource(run, f"rendered stereo of course {src.course} (seed {seed})", None)
    if src.source in ("kitti", "euroc") and src.path is None:
        raise ConfigError(f"--source {src.source} needs --path DATASET_FOLDER")
    if src.source == "kitti":
        from gslam_jax.datasets.kitti import KittiParams, find_sequence, kitti_frontend
        sequence = find_sequence(Path(src.path), src.sequence).name
        fe = KittiParams().frontend  # KITTI's own front-end defaults, with:
        fe = kitti_frontend(src.path, KittiParams(
            sequence=sequence, max_frames=src.max_frames,
            frontend=dataclasses.replace(fe, local_map=params, on_bad_frame=src.on_bad_frame,
                                         stereo=_stereo(config, fe.stereo))), progress=progress)
        print(fe.summary.text())
        return LoadedSource(fe.run, f"KITTI {src.path} sequence {sequence}", None)
    if src.source == "euroc":
        from gslam_jax.datasets.euroc import EurocParams, euroc_frontend
        from gslam_jax.vo.frontend import FrontEndParams
        default = FrontEndParams()
        fe = euroc_frontend(src.path, EurocParams(
            max_frames=src.max_frames,
            frontend=FrontEndParams(local_map=params, on_bad_frame=src.on_bad_frame,
                                    stereo=_stereo(config, default.stereo))), progress=progress)
        print(fe.summary.text())
        return LoadedSource(fe.run, f"EuRoC {src.path}", None)
    raise ConfigError(f"unknown source {src.source!r}")


def check_save_run(path: Path) -> None:
    """ConfigError, before any work, when ``--save-run`` cannot be written there."""
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"--save-run {path}: is a directory; give a file name (.npz)")
    parent = path.absolute().parent
    if not parent.is_dir():
        raise ConfigError(f"--save-run {path}: folder {parent} does not exist")
    try:  # the real test (os.access says yes to root on a read-only mount)
        fd, probe = tempfile.mkstemp(prefix=f".{path.name}.", dir=parent)
    except OSError as err:
        raise ConfigError(f"--save-run {path}: cannot write in {parent} "
                          f"({err.strerror or err})") from err
    os.close(fd)
    os.unlink(probe)


def save_run_file(path: Path, run) -> None:
    """Write ``run`` to ``path`` through a temporary file beside it, renamed when complete
    (a full disk leaves no truncated Run file); ResultsError naming ``--save-run``."""
    from gslam_jax.run import save_run

    path = Path(path)
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".partial",
                                   dir=path.absolute().parent)
        with os.fdopen(fd, "wb") as f:
            save_run(f, run)
        os.replace(tmp, path)
    except OSError as err:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)
        raise ResultsError(f"--save-run {path}: cannot write the Run ({err})") from err


def check_gps(gps: str | Path | None, run, seed: int | None, log=None):
    """The checked GPS input of ``--gps`` (``georeference.gps_input``) or None."""
    if gps is None:
        return None
    from gslam_jax.gps import georeference
    return georeference.gps_input(gps, run, 0 if seed is None else seed, log=log)


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
    resampling threshold (``threshold`` J, filter.resample_ratio); returns the Gamma-SLAM map's
    expected std."""
    from gslam_jax import metrics
    from gslam_jax.rbpf import cells
    from gslam_jax.app import plots

    slam_std = np.asarray(cells.expected_std(result.kmap, result.smap))
    vo_map = metrics.vo_only_map(run)
    vo_std = np.asarray(cells.expected_std(vo_map.k, vo_map.S))
    plots.save_map_png(out / "map.png", slam_std, result.map_origin, result.resolution,
                       path=result.path, title="Gamma-SLAM")
    plots.save_map_comparison_png(out / "maps_vo_vs_slam.png", vo_std, vo_map.origin, slam_std,
                                  result.map_origin, result.resolution, vo_path=result.vo_path,
                                  slam_path=result.path)
    plots.save_ess_png(out / "ess.png", result.ess, num_particles, resampled=result.resampled,
                       threshold=threshold)
    if run.ground_truth is not None:
        gt = metrics.ground_truth_in_map_frame(run.ground_truth, result.vo_path)
        if np.isfinite(gt).any():
            plots.save_ground_truth_png(out / "ground_truth.png", vo_std, vo_map.origin,
                                        slam_std, result.map_origin, result.resolution, gt,
                                        result.vo_path, result.path)
    return slam_std


def summarise(run, result, config: Config, description: str) -> dict:
    """The figures of ``summary.json`` (without the GPS figures)."""
    from gslam_jax import metrics

    summary = {
        "source": description,
        "frames": run.num_frames,
        "local_maps": run.num_local_maps,
        "distance_m": run.distance(),
        "particles": config.filter.particles,
        "estimate": config.filter.estimate,
        "resampling_events": int(np.sum(result.resampled)),
        "extent_violations": result.extent_violations,
        "empty_observations": result.empty_observations,
        "vo_failures": int(np.sum(run.vo_failed)) if run.vo_failed is not None else 0,
        "filter_seconds": result.seconds,
        "compile_seconds": result.compile_seconds,
    }
    if run.ground_truth is not None:
        paths = {"vo": result.vo_path, "slam": result.path}
        summary.update(metrics.errors_over_known_frames(paths, run.ground_truth))
        summary.update(metrics.drift_over_known_frames(paths, run.ground_truth))
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
                           "alpha_theta": fit.alpha_theta, "window_frames": fit.window,
                           "frames": fit.frames, "configured_over_fitted_along": along,
                           "configured_over_fitted_heading": heading}}


def write_outputs(out: Path, loaded: LoadedSource, result, config: Config,
                  gps_input=None) -> dict:
    """Every output file of a run into ``out`` (a staging folder); returns the summary.

    The TUM files carry the dataset's own clock (``Run.time_origin_ns`` added, e.g. EuRoC's
    nanosecond timestamps); ``ground_truth_tum.txt`` holds the frames with a finite
    ground-truth pose, beside the estimate, for evo. ``summary.json`` is written last."""
    from gslam_jax.config import config_to_toml
    from gslam_jax.io import save_map, write_kitti, write_tum

    run = loaded.run
    origin = run.time_origin_ns
    (out / "config.toml").write_text(config_to_toml(config))
    if loaded.sim_info is not None:
        (out / "simulation.json").write_text(json.dumps(loaded.sim_info.summary(), indent=2,
                                                        default=float))
    write_tum(out / "trajectory_tum.txt", run.timestamps, result.path, origin_ns=origin)
    write_kitti(out / "trajectory_kitti.txt", result.path)
    write_tum(out / "vo_tum.txt", run.timestamps, result.vo_path, origin_ns=origin)
    if run.ground_truth is not None:
        gt = np.asarray(run.ground_truth, np.float64)
        known = np.isfinite(gt).all(axis=1)
        if known.any():
            write_tum(out / "ground_truth_tum.txt", np.asarray(run.timestamps)[known], gt[known],
                      origin_ns=origin)
    save_map(out / "map.npz", result.kmap, result.smap, result.map_origin, result.resolution)
    np.savez_compressed(out / "trace.npz", ess=result.ess, exponent=result.exponent,
                        resampled=result.resampled,
                        updated=result.updated, log_lik=result.log_lik,
                        best_pose=result.best_pose, mean_pose=result.mean_pose)
    summary = summarise(run, result, config, loaded.description)
    slam_std = write_figures(out, run, result, config.filter.particles,
                             config.filter.resample_ratio)
    if gps_input is not None:
        from gslam_jax.gps import georeference
        summary["gps"] = georeference.write_gps_outputs(out, gps_input, run, result, slam_std)
    _write_json(out / "summary.json", summary)
    return summary


# print_summary notes motion noise that is more than this factor off the run's fitted noise
MOTION_NOISE_TOLERANCE = 3.0


def print_summary(summary: dict, run, result) -> None:
    """The console report of a finished run."""
    print(f"distance: {summary['distance_m']:.1f} m")
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
        else:
            print(f"ground truth: only {scored} of {run.num_frames} frames have a finite pose; "
                  "no RMS")
    fit = summary.get("motion_fit")
    if fit is not None:
        off = {k: fit[f"configured_over_fitted_{k}"] for k in ("along", "heading")}
        if any(not 1 / MOTION_NOISE_TOLERANCE <= r <= MOTION_NOISE_TOLERANCE
               for r in off.values()):
            print(f"note: the [motion] noise is {off['along']:.2g}x (along-track) and "
                  f"{off['heading']:.2g}x (heading) what this run's VO errors fit (alpha_d "
                  f"{fit['alpha_d']:.2g}, alpha_theta_d {fit['alpha_theta_d']:.2g}, alpha_theta "
                  f"{fit['alpha_theta']:.2g}); `gslam fit-motion` writes a config with them")
    print(f"resampling events: {summary['resampling_events']}, filter time "
          f"{result.seconds:.1f} s (+{result.compile_seconds:.1f} s first chunk incl. compile)")
    if result.extent_violations:
        print(f"WARNING: {result.extent_violations} particle updates reached the map edge")
    if result.empty_observations:
        print(f"note: {result.empty_observations} local maps had no informative cell "
              "(weights unchanged)")


def run_pipeline(src: Source, config: Config, out: Path | None = None, *,
                 overwrite: bool = False, gps: str | None = None, save_run: Path | None = None,
                 progress: ProgressFactory | None = None) -> tuple[Path, dict]:
    """``gslam run``: check every input, load the source, run Gamma-SLAM, write the results.

    Everything that can be checked before the work is (source options, local-map size, the
    results folder and ``save_run`` being writable, the GPS log); the results appear under
    ``out`` only when complete (``results.results_folder``). Returns (folder, summary).
    """
    from gslam_jax import slam

    bar = progress or (lambda label: None)
    check_source(src, config, gps)
    check_local_map_size(config)
    if save_run is not None:
        check_save_run(save_run)
    with results_folder(out, "run", overwrite=overwrite, command="gslam run") as folder:
        gps_log = None  # a GPS file is read before the front-end: its errors come first
        if gps is not None and str(gps) != "sim":
            from gslam_jax import gps as gps_mod
            gps_log = gps_mod.read_gps_log(gps)
        loaded = load_source(src, config, bar("front-end"))
        run = loaded.run
        if save_run is not None:
            save_run_file(save_run, run)
        gps_input = check_gps(gps, run, src.seed, log=gps_log)
        print(f"source: {loaded.description}: {run.num_frames} frames, {run.num_local_maps} "
              f"local maps, {run.distance():.1f} m")
        result = slam.run_slam(run, config, progress=bar("gamma-slam"))
        try:
            summary = write_outputs(folder.staging, loaded, result, config, gps_input)
        except OSError as err:
            raise ResultsError(f"{folder.name}: cannot write the results ({err}); nothing "
                               f"was written to {folder.target}") from err
        print_summary(summary, run, result)
    return folder.target, summary
