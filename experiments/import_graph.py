"""The package's shape from its own imports: top-level units, layers and import edges.

    python -m experiments.import_graph [--root gslam_jax] [--skip config:sim] [--json]

A unit is a module or a package directly under the root package (``slam.py``, ``rbpf/``); the
root's ``__init__.py`` is a unit of its own (``__init__``). An import edge is an ordered pair of
distinct units where a module of the first imports (at any depth of the file, function-level
imports included) a module of the second. The layers are the longest-path layering of the unit
graph: a unit that imports no other sits in layer 0, any other one layer above the highest unit
it imports (units on an import cycle are taken together, as one). The root's lazy exports
(names in strings, imported on first use) are not imports and are not counted. ``--skip A:B``
sets the edge from unit A to unit B aside (e.g. an upward import the layer test excuses) for
the layers; the edges are counted with it.
"""

from __future__ import annotations

import argparse
import ast
import json
import sys
from pathlib import Path

ROOT_UNIT = "__init__"


def module_name(path: Path, root: Path) -> str:
    """``root``-relative dotted name of the module at ``path`` ('' for the root's __init__)."""
    parts = [p for p in path.relative_to(root).with_suffix("").parts if p != "__init__"]
    return ".".join(parts)


def _exists(root: Path, dotted: str) -> bool:
    rel = dotted.replace(".", "/")
    return (root / rel).is_dir() or (root / (rel + ".py")).exists()


def imported_modules(path: Path, root: Path) -> set[str]:
    """Modules of the root package that ``path`` imports (dotted, relative to the root)."""
    package = root.name
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module and \
                node.module.split(".")[0] == package:
            base = node.module.removeprefix(package).lstrip(".")
            for alias in node.names:
                sub = f"{base}.{alias.name}".lstrip(".")
                found.add(sub if _exists(root, sub) else base)
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == package:
                    found.add(alias.name.removeprefix(package).lstrip("."))
    return found


def unit_of(module: str) -> str:
    """The top-level unit a module belongs to."""
    return module.split(".")[0] if module else ROOT_UNIT


def unit_graph(root: Path) -> dict[str, set[str]]:
    """unit -> the other units it imports."""
    graph: dict[str, set[str]] = {}
    for path in sorted(root.rglob("*.py")):
        unit = unit_of(module_name(path, root))
        targets = {unit_of(m) for m in imported_modules(path, root)}
        graph.setdefault(unit, set()).update(targets - {unit})
    return graph


def _components(graph: dict[str, set[str]]) -> dict[str, int]:
    """unit -> index of its strongly connected component (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    comp: dict[str, int] = {}
    stack: list[str] = []
    counter = [0, 0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w not in comp:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            while True:
                w = stack.pop()
                comp[w] = counter[1]
                if w == v:
                    break
            counter[1] += 1

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return comp


def layers(graph: dict[str, set[str]]) -> dict[str, int]:
    """unit -> its layer in the longest-path layering (cycles condensed)."""
    comp = _components(graph)
    members: dict[int, set[str]] = {}
    for v, c in comp.items():
        members.setdefault(c, set()).add(v)
    deps = {c: {comp[w] for v in vs for w in graph.get(v, ()) if w in comp} - {c}
            for c, vs in members.items()}
    level: dict[int, int] = {}

    def depth(c: int) -> int:
        if c not in level:
            level[c] = 1 + max((depth(d) for d in deps[c]), default=-1)
        return level[c]

    return {v: depth(comp[v]) for v in comp}


def shape(root: Path, skip: tuple[tuple[str, str], ...] = ()) -> dict:
    """Units, layers and edges of the package at ``root``, and the units by layer; the edges
    ``skip`` (unit, unit) are left out of the layering."""
    graph = unit_graph(root)
    layered = {u: t - {b for a, b in skip if a == u} for u, t in graph.items()}
    layer = layers(layered)
    by_layer: dict[int, list[str]] = {}
    for unit, n in layer.items():
        by_layer.setdefault(n, []).append(unit)
    cycles = [sorted(vs) for vs in _cycles(layered)]
    return {"root": str(root), "units": len(graph),
            "layers": 1 + max(layer.values(), default=-1),
            "edges": sum(len(t) for t in graph.values()),
            "by_layer": {n: sorted(by_layer[n]) for n in sorted(by_layer)},
            "cycles": cycles}


def _cycles(graph: dict[str, set[str]]) -> list[set[str]]:
    comp = _components(graph)
    groups: dict[int, set[str]] = {}
    for v, c in comp.items():
        groups.setdefault(c, set()).add(v)
    return [vs for vs in groups.values() if len(vs) > 1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", default="gslam_jax", help="the package's folder")
    ap.add_argument("--skip", action="append", default=[], metavar="A:B",
                    help="leave the import edge from unit A to unit B out of the layering")
    ap.add_argument("--json", action="store_true", help="print the whole shape as JSON")
    args = ap.parse_args(argv)
    skip = []
    for edge in args.skip:
        a, sep, b = edge.partition(":")
        if not (sep and a and b):
            print(f"--skip {edge}: expected UNIT:UNIT, e.g. config:sim", file=sys.stderr)
            return 2
        skip.append((a, b))
    root = Path(args.root).resolve()
    if not (root / "__init__.py").exists():
        print(f"--root {args.root}: not a package (no __init__.py)", file=sys.stderr)
        return 2
    s = shape(root, tuple(skip))
    if args.json:
        print(json.dumps(s, indent=1))
        return 0
    print(f"{s['units']} top-level units, {s['layers']} layers, {s['edges']} import edges "
          f"between units")
    for n, units in s["by_layer"].items():
        print(f"  layer {n}: {', '.join(units)}")
    for cycle in s["cycles"]:
        print(f"  import cycle (counted as one): {', '.join(cycle)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
