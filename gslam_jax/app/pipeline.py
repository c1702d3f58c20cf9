"""``gslam run`` as functions: a source -> Gamma-SLAM -> a complete results folder.

``cli`` parses arguments into a ``datasets.Source`` request and calls :func:`run_pipeline`;
table1, the experiments and the tests call the same steps: :func:`check_inputs` (every option
that can be checked before any work), :func:`prepare_source` (the registered source's
``load``: simulator, rendered stereo, KITTI, EuRoC or a Run file), :func:`check_gps` (the GPS
readings against the run, before the filter), ``slam.run_slam``, then
``outputs.write_outputs`` into a folder from ``results.results_folder``, which becomes the
target only once every file is written.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Callable

from gslam_jax.app.outfile import atomic_file, check_output_file
from gslam_jax.app.outputs import print_summary, write_outputs
from gslam_jax.app.results import ResultsError, results_folder
from gslam_jax.config import Config, ConfigError
from gslam_jax.datasets.registry import LoadedSource, Progress, Source, check_source
from gslam_jax.vo.localmap import localmap_params

__all__ = ["Source", "LoadedSource", "check_inputs", "prepare_source", "load_source",
           "check_save_run", "save_run_file", "check_local_map_size", "check_gps",
           "load_prior", "run_pipeline", "MAX_LOCAL_CELLS", "MIN_LOCAL_CELLS"]

ProgressFactory = Callable[[str], Progress]

# Local maps wider than this many cells per side are refused before the source runs: the
# paper's 10 m range at 0.16 m needs 128; at 1024 one local map alone is 25 MB of statistics
# and every update scatters up to a million cells per particle.
MAX_LOCAL_CELLS = 1024
# ... and local maps whose sensor range spans fewer cells than this per side: at [map] resolution
# 50 m a 10 m range falls in one cell, and the map is a few cells of kilometres, silently wrong.
MIN_LOCAL_CELLS = 8


def check_local_map_size(config: Config) -> None:
    """ConfigError, before any source runs, when a local map would exceed MAX_LOCAL_CELLS
    cells per side, or the sensor's range would span fewer than MIN_LOCAL_CELLS ([localmap]
    max_range or cells against [map] resolution)."""
    lm, res = config.localmap, config.map.resolution
    if 0 < lm.cells < MIN_LOCAL_CELLS:
        raise ConfigError(f"[localmap] cells = {lm.cells} gives local maps of fewer than "
                          f"{MIN_LOCAL_CELLS} cells per side; use at least {MIN_LOCAL_CELLS}, "
                          "or 0 to size them from [localmap] max_range")
    span = 2.0 * lm.max_range / res  # cells across the sensor's range
    if not span >= MIN_LOCAL_CELLS:
        raise ConfigError(f"[map] resolution {res:g} m against [localmap] max_range "
                          f"{lm.max_range:g} m spans {span:.3g} cells per side, fewer than "
                          f"{MIN_LOCAL_CELLS}: local maps this coarse say nothing about the "
                          f"terrain; use a [map] resolution of at most "
                          f"{2.0 * lm.max_range / MIN_LOCAL_CELLS:g} m (the paper's is 0.16 m) "
                          "or a longer [localmap] max_range")
    if not lm.cells and span == float("inf"):  # an absurd max_range over resolution
        raise ConfigError(f"[localmap] max_range {lm.max_range:g} m at [map] resolution {res:g} "
                          f"m gives local maps of more cells per side than a float holds, more "
                          f"than {MAX_LOCAL_CELLS}; use a coarser [map] resolution or a shorter "
                          "[localmap] max_range")
    L = localmap_params(config).size
    if L > MAX_LOCAL_CELLS:
        how = (f"[localmap] cells = {lm.cells}" if lm.cells else
               f"[localmap] max_range {lm.max_range:g} m at [map] resolution {res:g} m")
        # an absurd max_range makes L an integer beyond floats: its size in powers of ten
        side = str(L) if L < 10**6 else f"about 1e{len(str(L)) - 1}"
        mb = f"{L * L * 24 / 2**20:.0f}" if L < 10**6 else f"about 1e{len(str(L * L * 24)) - 7}"
        raise ConfigError(f"{how} gives local maps of {side} x {side} cells ({mb} "
                          f"MB of statistics each), more than {MAX_LOCAL_CELLS} per side; use a "
                          "coarser [map] resolution or a shorter [localmap] max_range")


def check_inputs(src: Source, config: Config, gps: str | None = None) -> None:
    """ConfigError, before any work, for source options the source would ignore or lacks
    (``datasets.registry.check_source``) and for local maps too large for the map."""
    check_source(src, config, gps)
    check_local_map_size(config)


def load_source(src: Source, config: Config, progress: Progress | None = None) -> LoadedSource:
    """The Run of ``src`` (after the front-end for image sources), its description and, for
    the simulator, its SimInfo: the registered source's ``load``. ``progress(done, total)``
    follows the frames."""
    return src.spec.load(src, config, progress)


def prepare_source(src: Source, config: Config, progress: Progress | None = None
                   ) -> LoadedSource:
    """``load_source``, then the one-line account of what was loaded."""
    loaded = load_source(src, config, progress)
    run = loaded.run
    print(f"source: {loaded.description}: {run.num_frames} frames, {run.num_local_maps} "
          f"local maps, {run.distance():.1f} m")
    return loaded


def check_save_run(path: Path, overwrite: bool = False) -> None:
    """OutputFileError, before any work, when ``--save-run`` cannot be written there (or
    exists, unless ``overwrite``)."""
    check_output_file(path, "--save-run", overwrite)


def save_run_file(path: Path, run) -> None:
    """Write ``run`` to ``path`` through a temporary file beside it, renamed when complete
    (a full disk leaves no truncated Run file); OutputFileError naming ``--save-run``."""
    from gslam_jax.run import save_run

    with atomic_file(path, "--save-run") as tmp:
        with open(tmp, "wb") as f:
            save_run(f, run)


def check_gps(gps: str | Path | None, run, seed: int | None, log=None):
    """The checked GPS input of ``--gps`` (``georeference.gps_input``) or None."""
    if gps is None:
        return None
    from gslam_jax.gps import georeference
    return georeference.gps_input(gps, run, 0 if seed is None else seed, log=log)


def load_prior(path: Path, start, start_sigma, config: Config):
    """The ``map_reuse.PriorMap`` of ``--prior-map PATH [--start X,Y,THETA] [--start-sigma ...]``,
    read and checked before any work: a MapFileError names an unusable map, a ConfigError a
    resolution other than [map] resolution (``map_reuse.check_prior``). Without ``start`` the start
    is located from the run once it is loaded (``map_reuse.locate_prior_start``)."""
    import numpy as np

    from gslam_jax.driver.map_reuse import PriorMap, check_prior
    from gslam_jax.gridmap import load_map

    path = Path(path)
    grid = load_map(path)
    file = path / "map.npz" if path.is_dir() else path
    sigma = np.zeros(3) if start_sigma is None else np.asarray(start_sigma, np.float64)
    start = None if start is None else np.asarray(start, np.float64)  # None: located later
    prior = PriorMap(grid, start, sigma, str(file.resolve()))
    check_prior(prior, config)
    if path.is_dir():  # a map its own run found doubled is reused, with a warning
        from gslam_jax.gridmap.merge import consistency_problem, load_run_folder
        problem = consistency_problem(load_run_folder(path))
        if problem is not None:
            print(f"warning: --prior-map {problem}; this run localises in it as it is",
                  file=sys.stderr)
    return prior


def run_pipeline(src: Source, config: Config, out: Path | None = None, *,
                 overwrite: bool = False, gps: str | None = None, save_run: Path | None = None,
                 progress: ProgressFactory | None = None, prior=None,
                 on_chunk: Callable | None = None, chunk: int | None = None,
                 map_check: bool = True) -> tuple[Path, dict]:
    """``gslam run``: check every input, load the source, run Gamma-SLAM, write the results.

    Everything that can be checked before the work is (source options, local-map size, the
    results folder and ``save_run`` being writable and new unless ``overwrite``, the GPS log); the results appear under
    ``out`` only when complete (``results.results_folder``). Returns (folder, summary). With a
    ``prior`` map (``load_prior``) the run starts in it and the results are in its frame.
    ``on_chunk`` and ``chunk`` go to ``slam.run_slam`` (e.g. ``app.viewer``: a callback after
    every ``chunk`` frames; the results do not depend on ``chunk``). With ``map_check`` the
    map is checked against itself (``consistency``: terrain the run mapped twice) and the
    verdict printed and recorded in ``summary.json`` (``map_consistency``).
    """
    from gslam_jax.driver import map_reuse, slam

    bar = progress or (lambda label: None)
    check_inputs(src, config, gps)
    if save_run is not None:
        check_save_run(save_run, overwrite)
    with results_folder(out, "run", overwrite=overwrite, command="gslam run") as folder:
        gps_log = None  # a GPS file is read before the front-end: its errors come first
        if gps is not None and str(gps) != "sim":
            from gslam_jax import gps as gps_mod
            gps_log = gps_mod.read_gps_log(gps)
        loaded = prepare_source(src, config, bar("front-end"))
        run = loaded.run
        if save_run is not None:
            save_run_file(save_run, run)
        gps_input = check_gps(gps, run, src.seed, log=gps_log)
        if prior is not None and prior.start is None:
            prior = map_reuse.locate_prior_start(prior, run, config)
            found = prior.located
            print(f"start located in the prior map: x {prior.start[0]:.2f} m, y "
                  f"{prior.start[1]:.2f} m, heading {math.degrees(prior.start[2]):.1f} deg (from "
                  f"the first {found['frames']} frames, z {found['z']:.1f} against runner-up "
                  f"{found['runner_up_z']:.1f}); particles spread by "
                  f"{[round(float(v), 3) for v in prior.start_sigma]}")
        if prior is not None:
            map_reuse.check_start_reaches(prior, run)
        result = slam.run_slam(run, config, progress=bar("gamma-slam"), prior=prior,
                               on_chunk=on_chunk, **({"chunk": chunk} if chunk else {}))
        consistency = None
        if map_check:
            from gslam_jax.gridmap.consistency import check_consistency
            consistency = check_consistency(run, result.path, progress=bar("map self-check"))
        if prior is not None:  # the VO-only map and the figures in the prior's frame too
            loaded = loaded._replace(run=map_reuse.rebase(run, prior.start))
        try:
            summary = write_outputs(folder.staging, loaded, result, config, gps_input, prior,
                                    consistency)
        except OSError as err:
            raise ResultsError(f"{folder.name}: cannot write the results ({err}); nothing "
                               f"was written to {folder.target}") from err
        print_summary(summary, run, result)
        if consistency is not None:
            print(consistency.describe())
        if prior is not None:
            p = summary["prior_map"]
            print(f"prior map: {p['prior_known_cells']} known cells, {p['cells_added']} added "
                  f"by this run ({p['path']})")
    return folder.target, summary
