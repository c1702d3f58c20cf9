"""The command line's shared pieces: argument types that name what they expected, the source
arguments every command that reads a log takes, and the config and Run they load.

Light on purpose (no JAX at import): ``gslam compare --exact`` must set XLA's flags before JAX
is imported."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from gslam_jax import choices
from gslam_jax.app.progress import ProgressBar
from gslam_jax.config import ConfigError, paper_differences
from gslam_jax.datasets.registry import Source, get_source, source_names
from gslam_jax.sim.courses import COURSES

__all__ = ["Deprecated", "Given", "SHARED", "add_config_arguments", "add_deprecated",
           "add_shared", "add_source_arguments", "attach_negative_values", "config_and_run",
           "config_overrides", "load_config", "nonnegative_int", "note", "pose", "pose_sigma",
           "positive_float", "positive_int", "seed", "source_request", "spelled", "topic",
           "use_course_path"]


def _integer(text: str, low: int, high: int | None, what: str, bounds: str) -> int:
    """An integer in [low, high) from ``text``, else a usage error saying ``what`` was expected
    (a non-number) or ``bounds`` (one out of range)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if value < low or (high is not None and value >= high):
        raise argparse.ArgumentTypeError(f"{bounds}, got {value}")
    return value


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1 (else a usage error)."""
    return _integer(text, 1, None, "a positive integer", "expected a positive integer")


def nonnegative_int(text: str) -> int:
    """argparse type: an integer >= 0 (else a usage error); 0 means automatic."""
    return _integer(text, 0, None, "an integer >= 0", "expected an integer >= 0 (0: automatic)")


def seed(text: str) -> int:
    """argparse type: a seed 0 <= seed < 2^32 (else a usage error)."""
    return _integer(text, 0, 2 ** 32, "an integer seed", "a seed must be in [0, 2^32)")


def topic(text: str) -> tuple[str, str]:
    """argparse type: ROLE=NAME (NAME may be empty: none) for --topic."""
    role, eq, name = text.partition("=")
    if not eq or not role.strip():
        raise argparse.ArgumentTypeError(f"expected ROLE=NAME (e.g. left=/cam0/image_raw), "
                                         f"got {text!r}")
    return role.strip(), name.strip()


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0 (else a usage error; float() accepts 'nan', 'inf')."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a finite positive number, got {text}")
    return value


def _triple(text: str, nonnegative: bool) -> tuple[float, float, float]:
    """Three finite comma-separated numbers (>= 0 with ``nonnegative``), else a usage error."""
    parts = text.split(",")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    what = "three numbers >= 0" if nonnegative else "three numbers"
    if len(values) != 3 or not all(math.isfinite(v) and (v >= 0 or not nonnegative)
                                   for v in values):
        raise argparse.ArgumentTypeError(f"expected {what} separated by commas, got {text!r}")
    return values  # type: ignore[return-value]


def pose(text: str) -> tuple[float, float, float]:
    """argparse type: X,Y,THETA (metres, radians)."""
    return _triple(text, nonnegative=False)


# Options whose value may begin with a minus sign (a pose west or south of the origin).
NEGATIVE_VALUE_OPTIONS = ("--start",)


def attach_negative_values(argv: list[str]) -> list[str]:
    """``--start -5,0,0`` as ``--start=-5,0,0``: argparse takes a separate value that begins
    with '-' and is not a plain number for an option of its own ("expected one argument")."""
    out: list[str] = []
    i = 0
    while i < len(argv):
        if argv[i] in NEGATIVE_VALUE_OPTIONS and i + 1 < len(argv) and \
                argv[i + 1].startswith("-") and argv[i + 1][1:2] in set("0123456789."):
            out.append(f"{argv[i]}={argv[i + 1]}")
            i += 2
            continue
        if argv[i] == "--":
            out.extend(argv[i:])
            break
        out.append(argv[i])
        i += 1
    return out


def pose_sigma(text: str) -> tuple[float, float, float]:
    """argparse type: SX,SY,STHETA standard deviations >= 0 (metres, radians)."""
    return _triple(text, nonnegative=True)


class Given(argparse.Action):
    """Store the value and note that the option was given (``<dest>_given``), not defaulted."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        setattr(namespace, self.dest, values)
        setattr(namespace, f"{self.dest}_given", True)


def note(text: str) -> None:
    """A note of the command line to the user (stderr), as ``note: TEXT``."""
    print(f"note: {text}", file=sys.stderr, flush=True)


class Deprecated(argparse.Action):
    """An old spelling that keeps working: stores its value as its ``dest`` (the option it
    stands for, or its own) and the spelling used as ``<dest>_spelled`` (for messages that
    name what the user wrote), and prints a note with ``advice`` (what to write instead).
    Hidden from ``--help``."""

    def __init__(self, option_strings, dest, advice: str = "", **kwargs):
        kwargs["help"] = argparse.SUPPRESS
        super().__init__(option_strings, dest, **kwargs)
        self.advice = advice

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        note(f"{option_string} is deprecated and will be removed: {self.advice}")
        setattr(namespace, self.dest, True if self.nargs == 0 else values)
        setattr(namespace, f"{self.dest}_spelled", option_string)


def spelled(args: argparse.Namespace, dest: str, option: str) -> str:
    """The option the user wrote for ``dest``: ``option``, or the old spelling given."""
    return getattr(args, f"{dest}_spelled", None) or option


def add_deprecated(p: argparse.ArgumentParser, option: str, advice: str, **kwargs) -> None:
    """``option`` on ``p`` as a :class:`Deprecated` spelling (``kwargs``: dest, type, nargs,
    choices as the option had them, so that its values are checked as before)."""
    p.add_argument(option, action=Deprecated, advice=advice, **kwargs)


# The options several commands share: one name, one dest, one help text, wherever they appear
# (tests/test_cli_vocabulary.py checks it). ``--out`` is a results folder in every command;
# one file is written by a ``--save-...`` option, or a ``--viewer-save`` recording.
SHARED: dict[str, dict] = {
    "--out": dict(type=Path, metavar="DIR", help=(
        "results folder: the command's files (its description and docs/formats.md list them) "
        "appear there only when complete (marker file COMPLETE); an existing, non-empty folder "
        "is refused unless --overwrite (default: results/<command>-<time> for run, search, "
        "tune and merge; no files for the others)")),
    "--overwrite": dict(action="store_true", help=(
        "replace an existing output: an --out folder as a whole once the new results are "
        "complete; a --save-run, --viewer-save or --save-config file once the new one is")),
    "--config": dict(type=Path, metavar="FILE.toml", help=(
        "TOML config (default: the built-in settings, `gslam config` prints them: the paper's, "
        "configs/paper.toml, except " + ", ".join(paper_differences()) + "); a Table I "
        "config's [course.<name>.*] tables apply to that simulated course in run, search, "
        "tune, fit-motion and table1, not in compare or config")),
    "--set": dict(action="append", metavar="SECTION.KEY=VALUE", help=(
        "override one config value after --config and its course tables (repeatable)")),
    "--particles": dict(type=positive_int, metavar="J", help=(
        "particles J: --set filter.particles=J (default: the config's; bench times each of "
        "several values, default 50 200 1000)")),
    "--unknown-cells": dict(choices=choices.UNKNOWN_CELLS, help=(
        "how the filter weighs cells its map has not observed: --set filter.unknown_cells="
        + "|".join(choices.UNKNOWN_CELLS) + " (default: the config's; bench times each of "
        "several values, default all)")),
    "--viewer-save": dict(type=Path, metavar="FILE.rrd", help=(
        "write the viewer's recording to this file (headless; open it with `rerun FILE.rrd`)")),
    "--save-config": dict(type=Path, metavar="FILE.toml", help=(
        "write the resulting config to this file (TOML, for --config); an existing file is "
        "refused unless --overwrite")),
}


def add_shared(p: argparse.ArgumentParser, *options: str, **changes) -> None:
    """The ``SHARED`` ``options`` on ``p``; ``changes`` (e.g. nargs="+", default) apply to
    each of them, never the name, dest or help."""
    for option in options:
        if {"help", "dest"} & set(changes):
            raise ValueError(f"{option}: a shared option keeps its help and dest")
        p.add_argument(option, **{**SHARED[option], **changes})


def add_config_arguments(p: argparse.ArgumentParser) -> None:
    """--config, --set and --particles, which ``config_overrides`` reads."""
    add_shared(p, "--config", "--set", "--particles")


def config_overrides(args: argparse.Namespace) -> list[str]:
    """The ``--set`` overrides of ``args``, then ``--particles J`` as filter.particles=J."""
    overrides = list(getattr(args, "set", None) or [])
    if getattr(args, "particles", None) is not None:
        overrides.append(f"filter.particles={args.particles}")
    return overrides


def use_course_path(args: argparse.Namespace) -> None:
    """``--course-path FILE`` is ``--source sim-path --path FILE``: set those, or a ConfigError
    for a Run file, another --source or a --path beside it."""
    what = f"--course-path {args.course_path}"
    if args.run_file is not None:
        raise ConfigError(f"{args.run_file}: a Run file is used as it is; {what} drives a "
                          "simulated world along a trajectory instead: give one of them")
    if getattr(args, "source_given", False) and args.source != "sim-path":
        raise ConfigError(f"{what} is --source sim-path --path FILE; it cannot be used with "
                          f"--source {args.source}")
    if args.path is not None:
        raise ConfigError(f"{what} and --path {args.path}: {what} is --source sim-path "
                          "--path FILE; name the trajectory once")
    args.source, args.path = "sim-path", args.course_path


def source_request(args: argparse.Namespace) -> Source:
    """The source request from the source arguments."""
    return Source(run_file=args.run_file, source=args.source, course=args.course,
                  path=args.path, sequence=args.sequence, seed=args.seed,
                  max_frames=args.max_frames, on_bad_frame=args.on_bad_frame,
                  noise_seed=args.noise_seed, topics=tuple(args.topic or ()))


def load_config(args: argparse.Namespace):
    """--config (with the [course.<name>.*] tables of a Table I config applied for a simulated
    --course), then the --set overrides."""
    from gslam_jax.config import layered_config

    simulated = getattr(args, "run_file", None) is None and get_source(args.source).simulated
    return layered_config(args.config, args.course if simulated else None, config_overrides(args),
                          COURSES)


def config_and_run(args: argparse.Namespace):
    """The config and the Run of a command's source arguments: the same checks and loading
    as ``gslam run`` (``pipeline.check_inputs``, ``pipeline.prepare_source``)."""
    from gslam_jax.app.pipeline import check_inputs, prepare_source

    config = load_config(args)
    src = source_request(args)
    check_inputs(src, config)
    return config, prepare_source(src, config, ProgressBar("front-end")).run


def add_source_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_file", nargs="?", type=Path, help="native .npz Run file (docs/formats.md)")
    names = source_names()
    p.add_argument("--source", choices=names, default=Source.source, action=Given,
                   help="where frames come from when no Run file is given: "
                   + "; ".join(f"{n}: {get_source(n).help}" for n in names)
                   + f" (default: {Source.source})")
    p.add_argument("--course", default="mars-yard-a", choices=COURSES, metavar="COURSE",
                   help=f"simulated course: {', '.join(COURSES)} (default mars-yard-a)")
    p.add_argument("--path", type=Path, help="the dataset of the source: " + "; ".join(
        f"--source {n}: {get_source(n).path}" for n in names if get_source(n).path))
    p.add_argument("--course-path", type=Path, metavar="FILE", help="drive a simulated world "
                   "along this trajectory (TUM or KITTI poses): the same as --source sim-path "
                   "--path FILE (--course picks the world kind and VO noise)")
    p.add_argument("--sequence", metavar="NN", help="the sequence to read (--source "
                   + "/".join(n for n in names if get_source(n).sequence)
                   + "), e.g. 00; needed when the dataset holds several")
    p.add_argument("--seed", type=seed, help="simulation seed, 0 <= seed < 2^32 (default 0); "
                   "only for simulated sources and --gps sim (the filter's seed is filter.seed)")
    p.add_argument("--noise-seed", type=seed, help="draw the VO and sensor noise from this seed "
                   "while the world and path stay those of --seed: the same terrain driven "
                   "again (--source sim; default: --seed)")
    p.add_argument("--topic", action="append", type=topic, metavar="ROLE=NAME",
                   help="the bag topic of a role (--source "
                   + "/".join(n for n in names if get_source(n).topics)
                   + "; repeatable): left, right, left_info, right_info, wheel, imu, "
                   "ground_truth; ROLE= for none (optional roles); default: picked when one "
                   "topic fits (docs/formats.md)")
    p.add_argument("--max-frames", type=positive_int, metavar="N",
                   help="use only the first N frames of the source (not with a Run file)")
    p.add_argument("--on-bad-frame", choices=choices.BAD_FRAME_POLICIES, default="error",
                   help="a missing/corrupt image stops the run (error) or is counted and bridged "
                   "by the fallback odometry")
    add_config_arguments(p)
