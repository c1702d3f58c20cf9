"""The path of one setting from the command line to the filter's kernel: the modules it visits,
in order, and how often it climbs back up a layer.

    python -m experiments.setting_trace [--set filter.particles=16] [--skip config:sim]

Runs ``gslam run --max-frames 3 --set SETTING --out TMP`` in this process under a profile hook
and records, in call order, the package's modules whose functions are called with the setting
in hand: an argument that is the command line holding it (a list of strings, or the parsed
``argparse.Namespace``), the ``Config``, its section (``FilterSection`` ...), or the filter's
static ``FilterConfig``. It stops at the first call into ``rbpf.kernel`` (the kernel's
``init``). Consecutive calls within one module count once. A climb is a step to a module whose
top-level unit sits in a higher layer than the current one's (the layers of
``experiments/import_graph.py``): the setting went back up (a return to a caller that then
calls down again). The package is whichever ``gslam_jax`` Python imports (PYTHONPATH), so the
same script traces another checkout.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import json
import sys
import tempfile
from pathlib import Path

TYPES = ("Config", "FilterSection", "MotionSection", "MapSection", "FilterConfig")


class _Reached(Exception):
    """The setting reached the kernel."""


def _import_graph():
    """``experiments/import_graph.py`` beside this file, whatever ``experiments`` resolves to."""
    path = Path(__file__).with_name("import_graph.py")
    spec = importlib.util.spec_from_file_location("_import_graph", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _carries(value, setting: str) -> bool:
    if isinstance(value, (list, tuple)) and any(isinstance(v, str) and setting in v
                                                 for v in value):
        return True
    if isinstance(value, argparse.Namespace):
        return any(_carries(v, setting) for v in vars(value).values())
    return type(value).__name__ in TYPES


def trace(setting: str) -> list[str]:
    """The package's modules (relative names) the setting ``setting`` (``SECTION.KEY=VALUE``)
    visits, from ``gslam run``'s command line to the kernel."""
    from gslam_jax.app.cli import main

    visited: list[str] = []

    def hook(frame, event, arg):
        if event != "call":
            return
        name = frame.f_globals.get("__name__", "")
        if not name.startswith("gslam_jax"):
            return
        code = frame.f_code
        params = code.co_varnames[:code.co_argcount + code.co_kwonlyargcount]
        if not any(_carries(frame.f_locals.get(p), setting.split("=")[0]) for p in params):
            return
        module = name.removeprefix("gslam_jax").lstrip(".") or "__init__"
        if not visited or visited[-1] != module:
            visited.append(module)
        if name == "gslam_jax.rbpf.kernel":
            raise _Reached

    with tempfile.TemporaryDirectory() as tmp:
        sys.setprofile(hook)
        try:
            with contextlib.redirect_stdout(sys.stderr):  # the run's own report
                main(["run", "--max-frames", "3", "--set", setting, "--out", f"{tmp}/out"])
        except _Reached:
            pass
        finally:
            sys.setprofile(None)
    return visited


def climbs(modules: list[str], layer: dict[str, int]) -> list[tuple[str, str]]:
    """The steps of ``modules`` to a module whose unit sits in a higher layer."""
    unit = lambda m: m.split(".")[0]  # noqa: E731
    return [(a, b) for a, b in zip(modules, modules[1:])
            if layer[unit(b)] > layer[unit(a)]]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--set", default="filter.particles=16", help="SECTION.KEY=VALUE")
    ap.add_argument("--skip", action="append", default=[], metavar="A:B",
                    help="leave the import edge from unit A to unit B out of the layering")
    ap.add_argument("--json", action="store_true", help="print the trace as JSON")
    args = ap.parse_args(argv)
    import gslam_jax

    graph = _import_graph()
    root = Path(gslam_jax.__file__).parent
    shape = graph.shape(root, tuple(tuple(e.split(":")) for e in args.skip))
    layer = {u: n for n, units in shape["by_layer"].items() for u in units}
    modules = trace(args.set)
    up = climbs(modules, layer)
    report = {"package": str(root), "setting": args.set, "modules": modules,
              "units": len({m.split(".")[0] for m in modules}),
              "layers": [layer[m.split(".")[0]] for m in modules],
              "climbs": len(up), "climbs_at": [f"{a} -> {b}" for a, b in up]}
    if args.json:
        print(json.dumps(report, indent=1))
        return 0
    print(f"{args.set} from the command line to the kernel ({root}): {len(modules)} modules "
          f"visited in {report['units']} units, {len(up)} climbs back up a layer")
    print("  " + " -> ".join(f"{m} ({n})" for m, n in zip(modules, report["layers"])))
    for a, b in up:
        print(f"  climb: {a} -> {b}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
