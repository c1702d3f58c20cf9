"""Where along a course each filter setting's error grows: position and heading error against
the truth every few metres of travel, for several settings on the same Run.

    python -m experiments.error_timeline --courses maze --sim-seeds 0 \
        --config configs/table1.toml \
        --variant motion-J20 filter.particles=20 \
        --variant informed-J20 filter.particles=20 filter.proposal=informed \
        --variant motion-J200 filter.particles=200

Every setting runs on the same Run (``--runs`` files or ``--courses`` x ``--sim-seeds``, as
``experiments.proposal_compare``), its ``--set`` overrides first, then the variant's own. The
errors are those of the reported path (``[filter] estimate``; ``--path mean`` or ``best`` for
the filter's estimate at each frame, which later frames have not corrected) and of the VO-only
path, each in the run's frame with no fit (both start at the true start pose), so an error made
at a corner stays visible where it was made. Per setting it also prints the whole path's RMS
after the rigid fit (Table I's figure), the first distance at which the heading error exceeds
``--heading-limit`` degrees, and that at which the position error first exceeds the VO's by
``--margin`` metres.

This is the measurement behind "what J = 20 lacks on the maze" (docs/notebook/results.md, Table I).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from experiments.common import add_case_arguments, cases_from_arguments, print_header
from gslam_jax.config import apply_overrides
from gslam_jax.driver import slam
from gslam_jax.driver.results import SlamResult
from gslam_jax.evaluation import metrics
from gslam_jax.gridmap.grid import arc_length
from gslam_jax.run import Run

__all__ = ["PATHS", "pose_errors", "first_exceeding", "timeline", "main"]


def pose_errors(path: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[T] position error (m) and [T] heading error (degrees, wrapped to (-180, 180]) of
    ``path`` against ``truth`` in the same frame, with no fit."""
    path, truth = np.asarray(path, np.float64), np.asarray(truth, np.float64)
    position = np.hypot(path[:, 0] - truth[:, 0], path[:, 1] - truth[:, 1])
    heading = np.degrees(np.angle(np.exp(1j * (path[:, 2] - truth[:, 2]))))
    return position, heading


def first_exceeding(values: np.ndarray, limit: float, dist: np.ndarray) -> float | None:
    """The distance of the first frame whose value exceeds ``limit`` (None: none does)."""
    over = np.flatnonzero(np.asarray(values) > limit)
    return float(dist[over[0]]) if over.size else None


PATHS = {"reported": "path", "mean": "mean_pose", "best": "best_pose"}


def timeline(run: Run, results: dict[str, SlamResult], every: float, heading_limit: float,
             margin: float, path: str = "reported") -> dict:
    """Rows every ``every`` metres of travel (the VO's and each setting's errors) and each
    setting's summary; ``results`` maps a setting's name to its run of ``run``. ``path``: the
    reported path (``[filter] estimate``, which knows the frames after each one), or the
    filter's own estimate at each frame, the weighted mean pose or the best particle's
    (``PATHS``), which does not."""
    truth = np.asarray(run.ground_truth, np.float64)
    known = np.isfinite(truth).all(axis=1)
    if not known.all():
        raise ValueError("the timeline needs ground truth at every frame")
    dist = arc_length(truth)
    vo_path = next(iter(results.values())).vo_path  # the same Run's: any setting's
    vo_pos, vo_head = pose_errors(vo_path, truth)
    paths = {name: getattr(res, PATHS[path]) for name, res in results.items()}
    errors = {name: pose_errors(p, truth) for name, p in paths.items()}
    marks = np.arange(0.0, dist[-1] + 1e-9, every)
    frames = np.unique(np.minimum(np.searchsorted(dist, marks), len(dist) - 1))
    rows = []
    for t in frames:
        row = {"frame": int(t), "distance_m": float(dist[t]),
               "vo": [float(vo_pos[t]), float(vo_head[t])]}
        row.update({name: [float(p[t]), float(h[t])] for name, (p, h) in errors.items()})
        rows.append(row)
    summary = {name: {
        "rms_after_fit_m": metrics.rms_after_fit(paths[name], truth),
        "heading_beyond_limit_at_m": first_exceeding(np.abs(errors[name][1]), heading_limit,
                                                     dist),
        "position_beyond_vo_at_m": first_exceeding(errors[name][0] - vo_pos, margin, dist),
        "final_position_error_m": float(errors[name][0][-1]),
        "seconds": res.seconds + res.compile_seconds,
    } for name, res in results.items()}
    summary["vo"] = {"rms_after_fit_m": metrics.rms_after_fit(vo_path, truth),
        "heading_beyond_limit_at_m": first_exceeding(np.abs(vo_head), heading_limit, dist),
        "final_position_error_m": float(vo_pos[-1])}
    return {"rows": rows, "summary": summary}


def _print(case: str, table: dict, names: list[str]) -> None:
    print(f"\n{case}: error in position (m) and heading (deg), no fit")
    print(f"{'distance':>9} {'VO':>15}" + "".join(f" {n:>17}" for n in names))
    for row in table["rows"]:
        print(f"{row['distance_m']:8.1f}m {row['vo'][0]:6.2f} {row['vo'][1]:+7.2f}"
              + "".join(f" {row[n][0]:8.2f} {row[n][1]:+7.2f}" for n in names))
    for name, s in table["summary"].items():
        head = s["heading_beyond_limit_at_m"]
        text = (f"  {name}: RMS after fit {s['rms_after_fit_m']:.3f} m, final error "
                f"{s['final_position_error_m']:.2f} m, heading beyond the limit from "
                + ("never" if head is None else f"{head:.0f} m"))
        if name != "vo":
            pos = s["position_beyond_vo_at_m"]
            text += (", position beyond VO's + margin from "
                     + ("never" if pos is None else f"{pos:.0f} m") + f" ({s['seconds']:.1f} s)")
        print(text, flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_case_arguments(ap)
    ap.add_argument("--variant", nargs="+", action="append", required=True,
                    metavar=("NAME", "SECTION.KEY=VALUE"),
                    help="a setting: its name, then its overrides (repeatable)")
    ap.add_argument("--every", type=float, default=10.0, help="metres of travel between rows")
    ap.add_argument("--heading-limit", type=float, default=3.0, help="degrees")
    ap.add_argument("--margin", type=float, default=0.5,
                    help="metres beyond the VO's position error")
    ap.add_argument("--path", choices=list(PATHS), default="reported",
                    help="the reported path ([filter] estimate, smoothed by later frames), or "
                    "the filter's estimate at each frame: its weighted mean or best particle")
    ap.add_argument("--out", help="write the figures as JSON here")
    args = ap.parse_args(argv)
    if not (args.every > 0 and math.isfinite(args.every)):
        ap.error(f"--every must be a positive number of metres, got {args.every}")
    names = [v[0] for v in args.variant]
    if len(set(names)) != len(names):
        ap.error(f"--variant names must differ, got {' '.join(names)}")
    print_header(args.set)
    figures = {}
    for case, run, config in cases_from_arguments(args):
        if run.ground_truth is None:
            ap.error(f"{case}: no ground truth")
        results = {v[0]: slam.run_slam(run, apply_overrides(config, v[1:]))
                   for v in args.variant}
        try:
            figures[case] = timeline(run, results, args.every, args.heading_limit, args.margin,
                                     args.path)
        except ValueError as err:
            ap.error(f"{case}: {err}")
        _print(case, figures[case], names)
    if args.out:  # the table above is the printed form; the file holds every row
        Path(args.out).write_text(json.dumps(figures, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
