"""The package's architecture as a test: every import goes down the layers, none across or up,
no module imports itself back through others (no import cycles), and the map stores are
reached only through their seam (``rbpf.maps``).

Layers, lowest first: the shared basics; settings; the paper's filter math and the Run
container; the front-end, the reference and finished maps (``gridmap``); the simulator and
evaluation; the sources; the host driver; GPS and parameter search; the application.
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "gslam_jax"

LAYERS = {
    "errors": 0, "choices": 0, "io": 0, "version": 0,
    "config": 1,
    "rbpf": 2, "run": 2,
    "vo": 3, "tiled": 3, "gridmap": 3,
    "sim": 4, "evaluation": 4,
    "datasets": 5,
    "driver": 6,
    "gps": 7, "tuning": 7,
    "app": 8,
    "": 9,  # gslam_jax/__init__.py: the public API gathers from every layer
}


def _module(path: Path) -> str:
    rel = path.relative_to(PACKAGE).with_suffix("")
    parts = [p for p in rel.parts if p != "__init__"]
    return ".".join(parts)


def _room(module: str) -> str:
    """The entry of LAYERS a module belongs to (its longest matching prefix)."""
    parts = module.split(".")
    for n in range(len(parts), 0, -1):
        if ".".join(parts[:n]) in LAYERS:
            return ".".join(parts[:n])
    return module


def _imports(path: Path) -> set[str]:
    """gslam_jax modules that ``path`` imports (relative to the package, '' for its root),
    at any depth of the file (function-level imports are dependencies too)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module and \
                node.module.split(".")[0] == "gslam_jax":
            base = node.module.removeprefix("gslam_jax").lstrip(".")
            for alias in node.names:
                sub = f"{base}.{alias.name}".lstrip(".")
                found.add(sub if (PACKAGE / sub.replace(".", "/")).exists()
                          or (PACKAGE / (sub.replace(".", "/") + ".py")).exists() else base)
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "gslam_jax":
                    found.add(alias.name.removeprefix("gslam_jax").lstrip("."))
        elif isinstance(node, ast.ImportFrom) and node.level:
            raise AssertionError(f"{path}: relative import; the package uses absolute imports")
    return found


@functools.cache
def _graph() -> dict[str, set[str]]:
    return {_module(p): _imports(p) for p in PACKAGE.rglob("*.py")}


def test_every_module_sits_in_a_layer():
    missing = sorted(m for m in _graph() if _room(m) not in LAYERS)
    assert not missing, f"modules outside the layer table: {missing}"


def test_imports_only_go_down_the_layers():
    wrong = []
    for module, imported in _graph().items():
        room = _room(module)
        for target in imported:
            other = _room(target)
            if other == room or other.startswith(room + ".") or room.startswith(other + "."):
                continue  # within one room
            if LAYERS[other] >= LAYERS[room]:
                wrong.append(f"{module} ({room}, layer {LAYERS[room]}) imports {target} "
                             f"({other}, layer {LAYERS[other]})")
    assert not wrong, "\n".join(sorted(wrong))


def test_no_import_cycles():
    graph = {m: {t for t in imp if t in _graph()} for m, imp in _graph().items()}
    state: dict[str, int] = {}

    def visit(m: str, stack: list[str]) -> None:
        state[m] = 1
        for t in sorted(graph.get(m, ())):
            if t == m or (m == "" or t == ""):
                continue
            if state.get(t) == 1 and not (t.startswith(m + ".") or m.startswith(t + ".")):
                cycle = stack[stack.index(t):] + [t] if t in stack else stack + [t]
                raise AssertionError("import cycle: " + " -> ".join(cycle))
            if t not in state:
                visit(t, stack + [t])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])



STORE_MODULES = {"rbpf.densestore", "rbpf.tilestore", "rbpf.tilebytes", "rbpf.tilesample",
                 "rbpf.windowstore"}
# Diagnostics that time a store by switching its own functions off: the one place past the seam.
STORE_DIAGNOSTICS = {"experiments/window_update_parts.py": {"rbpf.windowstore"}}


def test_the_map_stores_are_reached_only_through_rbpf():
    """The map-store seam (``rbpf.maps``): no module outside rbpf/, and no experiment but the
    store diagnostics named in ``STORE_DIAGNOSTICS``, imports a store's own modules."""
    experiments = PACKAGE.parent / "experiments"
    importers = {**{m: imp for m, imp in _graph().items() if m.split(".")[0] != "rbpf"},
                 **{f"experiments/{p.name}": _imports(p) for p in experiments.glob("*.py")}}
    wrong = sorted(f"{m} imports {t}" for m, imp in importers.items() for t in imp
                   if t in STORE_MODULES and t not in STORE_DIAGNOSTICS.get(m, ()))
    assert not wrong, "\n".join(wrong)


def test_every_experiment_imports():
    """The experiments follow the package's moves: each of them imports (a moved module left
    ``experiments/machine_floor.py`` importing ``gslam_jax.machine``, unnoticed)."""
    import importlib

    root = PACKAGE.parent / "experiments"
    failed = {}
    for path in sorted(root.glob("*.py")):
        if path.stem == "__init__":
            continue
        try:
            importlib.import_module(f"experiments.{path.stem}")
        except ImportError as err:
            failed[path.name] = str(err)
    assert not failed, failed
