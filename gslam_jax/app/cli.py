"""Command line: the ``gslam`` parser and ``main``; ``gslam run``, ``bench``, ``table1`` and
``compare`` here, the tuning commands in ``tuning_commands``, ``merge``, ``view`` and ``config``
in their own modules, the shared argument types and source arguments in ``arguments``."""

from __future__ import annotations

import argparse
import os
import signal
import sys
import warnings
from pathlib import Path

from gslam_jax import choices  # light (no JAX), as the next two
from gslam_jax.config import ConfigError  # light (no JAX), so --exact can still set XLA_FLAGS
from gslam_jax.errors import InputError
from gslam_jax.app.progress import ProgressBar
from gslam_jax.app.termination import Terminated, sigterm_as_exit
from gslam_jax.app import info, merge, tuning_commands, view
from gslam_jax.app.compile_cache import DEFAULT_MAX_MB, enable_compile_cache
from gslam_jax.app.arguments import (add_config_arguments, add_deprecated, add_shared,
                                     add_source_arguments, attach_negative_values,
                                     config_overrides, load_config, nonnegative_int, note, pose,
                                     pose_sigma, positive_float, positive_int, seed,
                                     source_request, use_course_path)
from gslam_jax.sim.courses import COURSES  # light (no JAX) too

__all__ = ["main", "console"]


def cmd_run(args: argparse.Namespace) -> int:
    from gslam_jax.app.pipeline import load_prior, run_pipeline

    config = load_config(args)
    prior = None
    if args.prior_map is not None:
        prior = load_prior(args.prior_map, args.start, args.start_sigma, config)
    elif args.start is not None or args.start_sigma is not None:
        raise ConfigError("--start and --start-sigma place the run in a prior map: give "
                          "--prior-map RUN_A too")
    with view.RunWatch.open(args.viewer, args.viewer_save, args.viewer_every,
                            overwrite=args.overwrite) as watch:
        out, _ = run_pipeline(source_request(args), config, args.out, overwrite=args.overwrite,
                              gps=args.gps, save_run=args.save_run, progress=ProgressBar,
                              prior=prior, on_chunk=watch.on_chunk, chunk=watch.chunk,
                              map_check=not args.no_map_check)
        watch.finish(out)
    print(f"results: {out}")
    return 0


def _into_folder(args: argparse.Namespace, kind: str, write) -> int:
    """``write(folder or None)``: into a results folder (``results.results_folder``) when
    --out is given, else with no folder."""
    if args.out is None:
        return write(None)
    from gslam_jax.app.results import results_folder

    with results_folder(args.out, kind, overwrite=args.overwrite,
                        command=f"gslam {kind}") as folder:
        code = write(folder.staging)
    print(f"results: {folder.target}")
    return code


def cmd_bench(args: argparse.Namespace) -> int:
    from gslam_jax.app.bench import main as bench_main

    def write(folder: Path | None) -> int:
        return bench_main(args.particles, args.local, args.map, args.repeats,
                          args.unknown_cells, folder / "bench.json" if folder else args.json,
                          course=args.course, course_particles=args.course_particles,
                          plot_path=folder / "bench.png" if folder else args.plot,
                          particle_block=args.particle_block, stores=args.store,
                          overwrite=args.overwrite)
    return _into_folder(args, "bench", write)


def cmd_table1(args: argparse.Namespace) -> int:
    from gslam_jax.app.table1 import main as table1_main

    def write(folder: Path | None) -> int:
        return table1_main(args.courses, args.seeds, args.particles, args.config,
                           folder / "table1.json" if folder else args.json, args.quick,
                           args.set or [], overwrite=args.overwrite)
    return _into_folder(args, "table1", write)


def cmd_compare(args: argparse.Namespace) -> int:
    if args.exact:
        if "jax" in sys.modules:
            raise SystemExit("--exact must be set before JAX is imported")
        # No fused multiply-adds in XLA, so float32 rounding matches NumPy's step for step.
        flags = os.environ.get("XLA_FLAGS", "")
        os.environ["XLA_FLAGS"] = (flags + " --xla_cpu_max_isa=AVX").strip()
    from gslam_jax.run import load_run
    from gslam_jax.config import load_table_config
    from gslam_jax.app.compare import (MAX_TILE_CELLS, CompareError, compare,
                                       default_resolution)

    # A Table I config works too: its shared settings are used, its [course.*] tables are not.
    config, per_course = load_table_config(args.config, COURSES)
    if per_course:
        print(f"note: {args.config}: compare uses the shared settings; the [course.<name>.*] "
              f"tables ({', '.join(per_course)}) are not applied")
    from gslam_jax.config import apply_overrides

    config = apply_overrides(config, config_overrides(args))
    run = load_run(args.run_file) if args.run_file else None
    tile_size = args.tile_size
    if args.tile_cells is not None:
        if tile_size is not None:
            raise ConfigError("--tile-cells and --tile-size (metres, deprecated) name the same "
                              "tile: give --tile-cells only")
        if args.tile_cells > MAX_TILE_CELLS:
            raise CompareError(f"--tile-cells {args.tile_cells}: more than {MAX_TILE_CELLS} "
                               "cells per side (the paper's 10 m tiles are 62 cells at 0.16 m)")
        tile_size = args.tile_cells * (run.resolution if run is not None
                                       else default_resolution())
    result = compare(run, config, particles=config.filter.particles,
                     unknown_cells=args.unknown_cells, tile_size=tile_size,
                     seed=config.filter.seed if args.seed is None else args.seed,
                     out_dir=args.out, store=args.store, pool_tiles=args.pool_tiles,
                     overwrite=args.overwrite)
    return 0 if result.get("agreement", {}).get("ok", True) else 1


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="gslam", description="Gamma-SLAM in JAX (Marks et al., Journal of Field Robotics "
        "2009)", epilog="Compiled filter programs are cached between runs in "
        "$XDG_CACHE_HOME/gslam-jax/jax (~/.cache/gslam-jax/jax), at most "
        f"{DEFAULT_MAX_MB} MB: GSLAM_JAX_CACHE=DIR puts the cache there, GSLAM_JAX_CACHE= "
        "(empty) turns it off, GSLAM_JAX_CACHE_MAX_MB=N bounds it; a JAX_COMPILATION_CACHE_DIR "
        "of your own is used as it is.")
    info.add_version(parser)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("run", help="run Gamma-SLAM on a Run file, a simulated course or a dataset",
                       description="Run Gamma-SLAM on a Run file, a simulated course or a "
                       "dataset. --out holds the trajectories, the map, the figures and "
                       "summary.json (docs/formats.md, \"Results folder\").")
    add_source_arguments(p)
    p.add_argument("--gps", help="GPS log (time, lat, lon, epe) to align the result to, read and "
                   "checked before the run; times are seconds on the run's clock (Run.timestamps: "
                   "EuRoC runs start at 0 at the first image, KITTI runs use times.txt). Readings "
                   "outside the run's time span are not used: at least 2 must fall inside it, "
                   "with a warning when fewer than half do. Or 'sim' for a simulated WAAS-like "
                   "receiver on a run with ground truth")
    p.add_argument("--save-run", type=Path, help="also write the Run (after the front-end) as "
                   ".npz; an existing file is refused unless --overwrite")
    p.add_argument("--prior-map", type=Path, metavar="RUN_A", help="map reuse: start every "
                   "particle with this map (a gslam run results folder or its map.npz, same "
                   "[map] resolution), localise in it and extend it; the results are in its frame")
    p.add_argument("--start", type=pose, metavar="X,Y,THETA", help="with --prior-map: the "
                   "run's start pose in the prior map's frame (metres, radians; a negative X "
                   "may follow directly: --start -5,0,0)")
    p.add_argument("--start-sigma", type=pose_sigma, metavar="SX,SY,STHETA", help="with "
                   "--prior-map: standard deviations of the start pose (metres, radians); the "
                   "particles start spread by them (default 0,0,0: all at --start)")
    p.add_argument("--no-map-check", action="store_true", help="skip checking the finished map "
                   "against itself (consistency: each revisited stretch of the path "
                   "scored against the map built before it; terrain mapped twice is reported and "
                   "recorded in summary.json's map_consistency, and gslam merge refuses it)")
    add_shared(p, "--out", "--overwrite")
    view.add_run_arguments(p, positive_int)
    p.set_defaults(func=cmd_run)

    tuning_commands.add_parsers(sub)
    _build_rest(sub)
    info.add_parser(sub)
    info.add_examples(sub)
    return parser


def _build_rest(sub) -> None:
    """bench, table1 and compare: commands with their own arguments."""
    p = sub.add_parser("bench", help="microseconds per particle per local-map update",
                       description="Microseconds per particle per local-map update, over every "
                       "combination of the values given. --out holds bench.json (every figure) "
                       "and bench.png (us per particle against J).")
    add_shared(p, "--particles", nargs="+", default=[50, 200, 1000])
    p.add_argument("--local", type=positive_int, nargs="+", default=[64],
                   help="local map sides, cells (default 64)")
    p.add_argument("--map", type=positive_int, nargs="+", default=[640],
                   help="global map sides, cells (default 640)")
    p.add_argument("--repeats", type=positive_int, default=10,
                   help="timed scans of each combination; the best is reported (default 10)")
    add_shared(p, "--unknown-cells", nargs="+", default=list(choices.UNKNOWN_CELLS))
    add_deprecated(p, "--mode", "use --unknown-cells, as compare and the config's "
                   "filter.unknown_cells", dest="unknown_cells", choices=choices.UNKNOWN_CELLS,
                   nargs="+")
    add_shared(p, "--out", "--overwrite")
    add_deprecated(p, "--json", "use --out DIR (bench.json in it)", dest="json", type=Path)
    add_deprecated(p, "--plot", "use --out DIR (bench.png in it)", dest="plot", type=Path)
    p.add_argument("--course", choices=COURSES, metavar="COURSE",
                   help="also time a whole simulated course after compilation "
                   "(e.g. mars-yard-a), default settings")
    p.add_argument("--course-particles", type=positive_int, default=200,
                   help="particles of the --course timing (default 200)")
    p.add_argument("--particle-block", type=nonnegative_int, nargs="+", default=[0],
                   help="particles per pass of the update (0: automatic); several values "
                   "compare block sizes in one process")
    p.add_argument("--store", choices=[s for s in choices.MAP_STORES if s != "auto"], nargs="+",
                   default=["dense"], help="map stores to time ([map] store; several: side by "
                   "side in one process)")
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser("table1", help="the paper's Table I on the five simulated courses",
                       description="The paper's Table I on the simulated courses. --out holds "
                       "table1.json (every row, with its config and the machine).")
    p.add_argument("--courses", nargs="+", default=list(COURSES), choices=COURSES,
                   metavar="COURSE", help=f"courses to run: {', '.join(COURSES)} (default all)")
    p.add_argument("--seeds", type=seed, nargs="+", default=[0, 1, 2],
                   help="simulation seeds, each course run once per seed (default 0 1 2)")
    add_config_arguments(p)
    add_shared(p, "--out", "--overwrite")
    add_deprecated(p, "--json", "use --out DIR (table1.json in it)", dest="json", type=Path)
    p.add_argument("--quick", action="store_true", help="Mars Yard A, one seed, J <= 100")
    p.set_defaults(func=cmd_table1)

    merge.add_parser(sub)
    view.add_parser(sub)

    p = sub.add_parser("compare", help="dense JAX filter vs the tiled copy-on-write reference",
                       description="The dense JAX filter against the tiled copy-on-write "
                       "reference on one Run, with the same random numbers (filter.seed). --out "
                       "holds compare.json and compare_fig4.png.")
    p.add_argument("run_file", nargs="?", type=Path, help="Run file (default: a simulated course)")
    add_config_arguments(p)
    add_shared(p, "--unknown-cells")
    p.add_argument("--tile-cells", type=positive_int, metavar="N", help="the reference's tile "
                   "side in map cells, as [map] tile counts them (default: the whole number of "
                   "cells nearest the paper's 10 m)")
    add_deprecated(p, "--tile-size", "use --tile-cells N (cells, as [map] tile); "
                   "--tile-size was metres", dest="tile_size", type=positive_float)
    add_deprecated(p, "--seed", "use --set filter.seed=N (the filter's seed, as in gslam run)",
                   dest="seed", type=seed)
    add_shared(p, "--out", "--overwrite")
    p.add_argument("--exact", action="store_true",
                   help="disable XLA's fused multiply-adds so both filters round identically")
    p.add_argument("--store", choices=choices.MAP_STORES,
                   help="the JAX filter's map store (default: the config's [map] store)")
    p.add_argument("--pool-tiles", type=nonnegative_int, help="shared store pool size "
                   "(default: the config's [map] pool_tiles; 0: automatic)")
    p.set_defaults(func=cmd_compare)


def _out_of_memory(err: BaseException) -> bool:
    """XLA's RESOURCE_EXHAUSTED (an allocation the process may not make) or a MemoryError."""
    return isinstance(err, MemoryError) or "RESOURCE_EXHAUSTED" in str(err)[:2000]


def _show_note(message, category, filename, lineno, file=None, line=None) -> None:
    """``warnings.showwarning`` of the command line: a warning as the CLI's own note, without
    the file and source line of the code that raised it (a library's non-UserWarning keeps its
    category's name)."""
    kind = "" if issubclass(category, UserWarning) else f"{category.__name__}: "
    note(f"{kind}{message}")


def main(argv: list[str] | None = None) -> int:
    """``gslam``: parse (a negative value attached to its option, ``attach_negative_values``),
    turn on the compilation cache (``compile_cache``), run the command with Python warnings
    shown as notes and SIGTERM as exit 143 (``termination``); the exit status."""
    argv = attach_negative_values(sys.argv[1:] if argv is None else list(argv))
    args = build_parser().parse_args(argv)
    try:
        enable_compile_cache()
    except ValueError as err:
        print(f"gslam: error: {err}", file=sys.stderr)
        return 2
    with warnings.catch_warnings():
        warnings.showwarning = _show_note
        try:
            with sigterm_as_exit():  # every file a command stages is removed on SIGTERM too
                return _run_command(args)
        except Terminated as err:
            return int(err.code)


def _run_command(args: argparse.Namespace) -> int:
    try:
        if getattr(args, "course_path", None) is not None:
            use_course_path(args)
        return args.func(args)
    except (InputError, FileNotFoundError) as err:
        print(f"gslam: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("gslam: interrupted; no results were written", file=sys.stderr)
        return 130
    except Exception as err:  # noqa: BLE001 - only memory exhaustion is reported, not hidden
        if not _out_of_memory(err):
            raise
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        print(f"gslam: error: out of memory ({first[:300]}); the process may use less memory "
              "than the machine has (a ulimit -v or container limit: check `ulimit -a`): use "
              "fewer [filter] particles, a coarser [map] resolution or a smaller [map] margin",
              file=sys.stderr)
        return 3


def console() -> None:
    """The ``gslam`` script: ``main``, then exit. After Ctrl-C or SIGTERM the process ends
    without Python's teardown, which can crash (SIGSEGV) while XLA threads are still compiling
    or running (``termination``)."""
    code = main()
    if code in (130, 128 + signal.SIGTERM):
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    console()
