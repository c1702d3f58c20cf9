"""``gslam merge``: runs' maps aligned (``gridmap.align``) and summed (eq. 14) into the frame
of the first, written as a results folder: the merged map, each run's frame pose with its
uncertainty, each run's path in the merged frame and a figure."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from gslam_jax.app.arguments import add_shared
from gslam_jax.app.outputs import json_ready
from gslam_jax.app.results import results_folder, writing

__all__ = ["add_parser", "cmd_merge", "write_merge"]


def add_parser(sub) -> None:
    p = sub.add_parser("merge", help="align runs' maps by the gamma likelihood and merge them "
                       "into the first run's frame",
                       description="Align runs' maps by the gamma likelihood and merge them "
                       "into the first run's frame. --out holds map.npz (the merged map), "
                       "map.png, each run's path in that frame (TUM) and summary.json (each "
                       "run's frame pose and its uncertainty; docs/formats.md).")
    p.add_argument("runs", nargs="+", metavar="RUN",
                   help="gslam run results folders (or map.npz files); the first sets the frame")
    p.add_argument("--no-gps", action="store_true",
                   help="ignore the runs' GPS alignments (by default, where both runs have one "
                        "it is a prior that narrows the search)")
    p.add_argument("--allow-inconsistent", action="store_true",
                   help="merge a run whose map failed its own run's consistency check (terrain "
                        "mapped twice; summary.json's map_consistency); refused by default")
    add_shared(p, "--out", "--overwrite")
    p.set_defaults(func=cmd_merge)


def cmd_merge(args: argparse.Namespace) -> int:
    from gslam_jax.gridmap.merge import load_run_folder, merge_runs

    if len(args.runs) < 2:
        raise SystemExit("gslam merge: error: give at least two runs")
    from gslam_jax.gridmap.merge import check_consistent, check_distinct

    runs = [load_run_folder(r) for r in args.runs]
    check_distinct(runs)  # before any folder is made
    if not args.allow_inconsistent:
        for run in runs:
            check_consistent(run)
    for run in runs:
        if run.unchecked is not None:
            print(f"note: {run.name}: {run.unchecked}: whether its map is consistent with "
                  "itself is not known, so that check is skipped for it (merge its complete "
                  "results folder to have it checked)", file=sys.stderr)
    with results_folder(args.out, "merge", overwrite=args.overwrite,
                        command="gslam merge") as folder:
        merged = merge_runs(runs, use_gps=not args.no_gps,
                            allow_inconsistent=args.allow_inconsistent,
                            progress=lambda i, n: print(f"merge: aligned {i}/{n}", flush=True))
        with writing(folder):
            summary = write_merge(folder.staging, runs, merged)
    for entry in summary["runs"][1:]:
        al = entry["alignment"]
        print(f"{entry['name']}: x {al['pose'][0]:.3f} m, y {al['pose'][1]:.3f} m, heading "
              f"{al['heading_deg']:.2f} deg (std {al['std_m'][0]:.3f} m, {al['std_m'][1]:.3f} m, "
              f"{al['std_heading_deg']:.3f} deg), z {al['z']:.1f} against runner-up "
              f"{al['runner_up_z']:.1f}, {al['overlap_cells']} cells overlapping")
    print(f"merged map: {summary['known_cells']} known cells; results: {folder.target}")
    return 0


def write_merge(out: Path, runs, merged) -> dict:
    """The merge's files in ``out``: map.npz (merged), map.png (each run placed, then the
    merge), trajectory_<i>_<name>_tum.txt (each run's path in the merged frame), summary.json."""
    from gslam_jax.app import plots
    from gslam_jax.gridmap import save_map, transform
    from gslam_jax.gridmap.merge import place_path
    from gslam_jax.io import write_tum
    from gslam_jax.rbpf import cells

    save_map(out / "map.npz", merged.grid)
    res = merged.grid.resolution
    panels = []
    entries = []
    for i, (run, pose, al) in enumerate(zip(runs, merged.poses, merged.alignments)):
        placed = transform(run.grid, pose, like=merged.grid) if i else run.grid
        path = None
        entry = {"name": run.name, "known_cells": int(run.grid.known.sum()),
                 "pose_in_merged_frame": [float(v) for v in pose]}
        if run.path is not None:
            path = place_path(pose, run.path)
            name = f"trajectory_{i}_{run.name}_tum.txt"
            write_tum(out / name, run.times, path)
            entry["trajectory"] = name
        if al is not None:
            entry["alignment"] = al.summary()
        entries.append(entry)
        std = np.asarray(cells.expected_std(placed.k, placed.S))
        panels.append((f"{run.name}" + (" placed" if i else ""), std,
                       (*placed.origin, placed.heading), path))
    std = np.asarray(cells.expected_std(merged.grid.k, merged.grid.S))
    panels.append(("merged", std, (*merged.grid.origin, merged.grid.heading), None))
    plots.save_maps_png(out / "map.png", panels, res)
    summary = {"runs": entries, "known_cells": int(merged.grid.known.sum()),
               "resolution": res, "frame": f"the map frame of {runs[0].name}"}
    (out / "summary.json").write_text(json.dumps(json_ready(summary), indent=2,
                                                 allow_nan=False))
    return summary
