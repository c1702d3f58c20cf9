"""``gslam --version``, ``gslam config`` and the examples that end every command's ``--help``.

Nothing here imports JAX: ``--version`` reads the installed packages' versions from their
metadata, and ``gslam config`` only needs the settings layer.
"""

from __future__ import annotations

import argparse
from importlib import metadata
from pathlib import Path

from gslam_jax.app.arguments import add_deprecated, add_shared, spelled
from gslam_jax.version import __version__

__all__ = ["EXAMPLES", "add_examples", "add_parser", "add_version", "cmd_config",
           "version_text"]

# The distributions --version names: the array stack, and OpenCV under any of its wheels.
_PACKAGES = (("jax", ("jax",)), ("jaxlib", ("jaxlib",)), ("numpy", ("numpy",)),
             ("opencv", ("opencv-python-headless", "opencv-python", "opencv-contrib-python",
                         "opencv-contrib-python-headless")))

# Two or three examples per command, shown at the end of its --help.
EXAMPLES = {
    "run": """\
  gslam run                                        # the simulated Mars Yard A course
  gslam run --source kitti --path DIR --sequence 00
  gslam run log.npz --out results/log --overwrite  # a Run file, into a chosen folder""",
    "search": """\
  gslam search --space configs/search_example.toml --n 64 --objective rms
  gslam search --space configs/search_example.toml --course maze --out results/maze-search""",
    "tune": """\
  gslam tune --objective supervised --steps 50 --out tuned
  gslam tune --params alpha_d,alpha_theta --optimizer sgd --lr 0.01 --steps 20""",
    "fit-motion": """\
  gslam fit-motion --source kitti --path DIR --sequence 00 --save-config fitted.toml
  gslam fit-motion log.npz --window 10     # errors summed over windows of 10 frames
  gslam fit-motion log.npz --evidence --save-config fitted.toml   # no ground truth needed""",
    "bench": """\
  gslam bench                              # J = 50, 200, 1000 on a 640-cell map
  gslam bench --particles 200 --store dense shared --course mars-yard-a""",
    "table1": """\
  gslam table1 --quick                     # Mars Yard A, one seed, J <= 100
  gslam table1 --config configs/table1.toml --out results/table1""",
    "merge": """\
  gslam merge results/A results/B --out results/merged
  gslam merge results/A/map.npz results/B/map.npz --no-gps""",
    "view": """\
  gslam view results/run                   # the finished run in the Rerun viewer
  gslam view results/run --viewer-save run.rrd  # ... written to a recording instead""",
    "compare": """\
  gslam compare --exact                    # both filters round identically
  gslam compare log.npz --store shared --out results/compare""",
    "config": """\
  gslam config                             # the default config as TOML
  gslam config --save-config my.toml       # ... written to a file, to edit for --config
  gslam config --config configs/kitti.toml --set filter.particles=100""",
}


def version_text() -> str:
    """``gslam <version>`` and the versions of jax, jaxlib, numpy and OpenCV (from the installed
    packages' metadata: nothing is imported)."""
    found = []
    for name, dists in _PACKAGES:
        for dist in dists:
            try:
                found.append(f"{name} {metadata.version(dist)}")
                break
            except metadata.PackageNotFoundError:
                continue
        else:
            found.append(f"{name} not installed")
    return f"gslam {__version__} ({', '.join(found)})"


class _Version(argparse.Action):
    """``--version``: print ``version_text()`` and exit (looked up only when asked for)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS,
                 help="print the versions of gslam, jax, numpy and OpenCV and exit"):
        super().__init__(option_strings, dest, nargs=0, default=default, help=help)

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        print(version_text())
        parser.exit()


def add_version(parser: argparse.ArgumentParser) -> None:
    """``--version`` on the top-level parser."""
    parser.add_argument("--version", action=_Version)


def add_parser(sub) -> None:
    p = sub.add_parser("config", help="print the default config as TOML (or the config that "
                       "--config and --set make), or write it with --save-config")
    add_shared(p, "--config", "--set")
    add_shared(p, "--save-config", "--overwrite")  # instead of printing it
    add_deprecated(p, "--out", "use --save-config FILE.toml (--out is a results folder in "
                   "the other commands)", dest="save_config", type=Path)
    p.set_defaults(func=cmd_config)


def cmd_config(args: argparse.Namespace) -> int:
    from gslam_jax.app.outfile import check_output_file, write_text_atomic
    from gslam_jax.config import config_to_toml, layered_config
    from gslam_jax.sim.courses import COURSES

    out, option = args.save_config, spelled(args, "save_config", "--save-config")
    if out is not None:  # a folder, a read-only place, an existing file: refused first
        check_output_file(out, option, args.overwrite)
    text = config_to_toml(layered_config(args.config, None, args.set, COURSES), comments=True)
    if out is None:
        print(text, end="")
    else:
        write_text_atomic(out, text, option)
        print(f"config: {out} (for --config)")
    return 0


def add_examples(sub) -> None:
    """End the ``--help`` of every command in ``sub`` with its EXAMPLES (as written)."""
    for name, parser in sub.choices.items():
        if name in EXAMPLES:
            parser.epilog = "examples:\n" + EXAMPLES[name]
            parser.formatter_class = argparse.RawDescriptionHelpFormatter
