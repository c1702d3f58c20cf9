"""The command line's shared pieces: argument types that name what they expected, the source
arguments every command that reads a log takes, and the config and Run they load.

Light on purpose (no JAX at import): ``gslam compare --exact`` must set XLA's flags before JAX
is imported."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from gslam_jax import choices
from gslam_jax.app.progress import ProgressBar
from gslam_jax.config import ConfigError, paper_differences
from gslam_jax.datasets.registry import Source, get_source, source_names
from gslam_jax.sim.courses import COURSES

__all__ = ["Given", "add_source_arguments", "attach_negative_values", "config_and_run", "load_config", "nonnegative_int",
           "pose", "pose_sigma", "positive_float", "positive_int", "seed", "source_request",
           "topic", "use_course_path"]


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
    return layered_config(args.config, args.course if simulated else None, args.set, COURSES)


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
    p.add_argument("--config", type=Path, help="TOML config (defaults: the paper's settings, "
                   "configs/paper.toml, except " + ", ".join(paper_differences()) + ")")
    p.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE",
                   help="override one config value (repeatable)")
