"""The rows of ``experiments.loop_closure`` pooled: closure rates per (proposal, J) and loop
length, the longest loop closed in a share of seeds, the split by the cloud before the revisit,
and the plot of closure probability against loop length (the circles and the real paths' cuts
as separate curves)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["VERDICTS", "summary", "print_summary", "family", "curves", "plot",
           "read_rows"]

# --verdict: the path a verdict is of
VERDICTS = {"best": "closed", "mode": "mode_closed", "mode_mean": "mode_mean_closed"}


def summary(rows: list[dict], share: float = 0.8, verdict: str = "best") -> dict:
    """Per "proposal J=..": the closure rate at each length and the longest length closed in
    at least ``share`` of its runs (None when none is), by the verdict on the best particle's
    path, (``verdict = "mode"``) on the densest particle's or (``"mode_mean"``) on the mean
    over its 1 m neighbourhood; and "approach": [closed, runs]
    of the runs that had a particle within 1 m of the truth before the revisit ("near") and
    of those that had none ("none"), over the runs that recorded their cloud."""
    field, out = VERDICTS[verdict], {}
    for r in rows:
        if r["closed"] is not None and field not in r:
            raise ValueError(f"{r['loop']} seed {r['seed']} {r['proposal']} J={r['particles']}: "
                             f"no {verdict} verdict (a run from before it was recorded)")
    for key in sorted({(r["proposal"], r["particles"]) for r in rows}):
        mine = [r for r in rows if (r["proposal"], r["particles"]) == key
                and r["closed"] is not None]
        rates = {}
        for length in sorted({r["length_m"] for r in mine}):
            got = [r[field] for r in mine if r["length_m"] == length]
            rates[length] = (sum(got) / len(got), len(got))
        ok = [length for length, (rate, _) in rates.items() if rate >= share]
        approach = {"near": [0, 0], "none": [0, 0]}
        for r in mine:
            if "approach_within_1m" in r:
                side = approach["near" if r["approach_within_1m"] > 0 else "none"]
                side[0], side[1] = side[0] + bool(r[field]), side[1] + 1
        out[f"{key[0]} J={key[1]}"] = {"rates": rates, "longest": max(ok) if ok else None,
                                       "approach": approach}
    return out


def family(row: dict) -> str:
    """"circles" for the synthetic circuits (``loop_paths.circle_loop``), "real paths" for the
    cuts of pose files: two families whose closure rates need not order by length together."""
    return "circles" if row["loop"].startswith("circle-") else "real paths"


def curves(rows: list[dict], verdict: str = "best") -> dict[tuple[str, str], tuple]:
    """(series, family) -> (loop lengths, closure rates) as the plot draws them: a series per
    (proposal, J) (``summary``'s names) and "VO only", for each ``family`` apart."""
    out = {}
    for fam in sorted({family(r) for r in rows}):
        mine = [r for r in rows if family(r) == fam]
        for name, s in summary(mine, verdict=verdict).items():
            lengths = sorted(s["rates"])
            out[(name, fam)] = (lengths, [s["rates"][x][0] for x in lengths])
        vo = {}
        for r in mine:
            if r["closed"] is not None:
                vo.setdefault(r["length_m"], {})[(r["loop"], r["seed"])] = r["vo_closed"]
        lengths = sorted(vo)
        out[("VO only", fam)] = (lengths, [float(np.mean(list(vo[x].values())))
                                           for x in lengths])
    return out


def plot(rows: list[dict], path: Path, verdict: str = "best") -> None:
    """Closure probability against loop length (``curves``): a colour per (proposal, J), VO
    only in black; circles solid with dots, the real paths' cuts dotted with squares (each cut
    is one loop of one path, so their curve need not fall with length as the circles' does)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    got = curves(rows, verdict)
    names = sorted({name for name, _ in got if name != "VO only"})
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for (name, fam), (lengths, rates) in got.items():
        colour = ({"color": "k", "alpha": 0.5} if name == "VO only"
                  else {"color": f"C{names.index(name)}"})
        ax.plot(lengths, rates, "o-" if fam == "circles" else "s:", label=f"{name}, {fam}",
                **colour)
    ax.set_xscale("log")
    ax.set_ylim(-0.05, 1.05)
    ax.set_xlabel("loop length (m)")
    ax.set_ylabel("closure probability (share of seeds)")
    ax.set_title(f"revisit error and map offset <= 1 m ({verdict} particle's path)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def print_summary(rows: list[dict], verdict: str = "best") -> dict:
    """Print ``summary(rows, verdict=verdict)``, a line per (proposal, J), and return it."""
    print(f"\nclosure rate per loop length (share of seeds closed, runs; {verdict} particle's "
          "path):")
    summ = summary(rows, verdict=verdict)
    for name, s in summ.items():
        rates = ", ".join(f"{x:g} m {r:.0%} ({n})" for x, (r, n) in s["rates"].items())
        longest = "none" if s["longest"] is None else f"{s['longest']:g} m"
        print(f"  {name}: {rates}; longest closed in >= 80 %: {longest}")
        (near_c, near_n), (none_c, none_n) = s["approach"]["near"], s["approach"]["none"]
        if near_n + none_n:
            print(f"    closed with a particle within 1 m before the revisit: {near_c}/{near_n}"
                  f"; with none: {none_c}/{none_n}")
    return summ


def read_rows(files: list[Path]) -> list[dict]:
    """The result rows of ``--json`` files, in order. A run (loop, seed, proposal, J) found in
    two files, or a file that is not such a JSON, is an error naming the file."""
    rows, seen = [], {}
    for file in files:
        try:
            got = json.loads(Path(file).read_text())["rows"]
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise SystemExit(f"{file}: not a loop_closure --json file ({e})")
        for r in got:
            key = (r["loop"], r["seed"], r["proposal"], r["particles"])
            if key in seen:
                raise SystemExit(f"{file}: run {key} is also in {seen[key]}")
            seen[key] = file
            rows.append(r)
    return rows
