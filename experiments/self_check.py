"""The map's check against itself (``consistency``) against the truth, on the simulator.

    python -m experiments.self_check --cache maps --courses mars-yard-a arroyo-a maze \
        --trials 10 --json self_check.json

Reads the maps and paths that ``experiments.map_merge --cache maps`` keeps (A: the course with
sim seed 0; B trial i: VO and sensor noise seed 100 + i), simulates each Run again (the local
maps do not depend on the start pose) and checks each map at its own path, and A's Run at its
true poses. Each revisited stretch is judged by the truth as well, which the check does not see:
for each of its frames, the revisit error (``loops.revisit_error``: the frame's position seen
from the nearest earlier frame within 2 m on the true path, estimate against truth); a stretch
whose median is over 1 m is mapped twice by the truth's account. Prints per map and per course.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from gslam_jax.config import Config
from gslam_jax.datasets.sim import simulate_run
from gslam_jax.driver.machine import environment
from gslam_jax.evaluation.loops import revisit_error
from gslam_jax.gridmap.consistency import check_consistency
from gslam_jax.gridmap.grid import arc_length
from gslam_jax.vo.localmap import localmap_params

TRUTH_TOLERANCE = 1.0  # metres of median revisit error over which the truth calls a stretch doubled


def truth_error(true: np.ndarray, est: np.ndarray, first: int, last: int, gap_m: float,
                radius: float = 2.0) -> float | None:
    """Median over frames first..last of the revisit error against the nearest earlier frame
    (at least ``gap_m`` of estimated travel before ``first``) within ``radius`` on the true
    path; None when no frame has one."""
    arc = arc_length(est)
    earlier = np.flatnonzero(arc < arc[first] - gap_m)
    errors = []
    for j in range(first, last + 1):
        dist = np.hypot(*(true[earlier, :2] - true[j, :2]).T)
        k = int(np.argmin(dist))
        if dist[k] <= radius:
            errors.append(revisit_error(true, est, int(earlier[k]), j))
    return float(np.median(errors)) if errors else None


def check_map(course: str, noise_seed: int | None, poses: np.ndarray | None,
              config: Config) -> dict:
    """One map checked at ``poses`` (None: the Run's true poses) and judged by the truth."""
    run, _ = simulate_run(course, seed=0, params=localmap_params(config), noise_seed=noise_seed)
    true = np.asarray(run.ground_truth, np.float64)
    est = true if poses is None else np.asarray(poses, np.float64)
    t0 = time.perf_counter()
    check = check_consistency(run, est)
    seconds = time.perf_counter() - t0
    revisits = []
    for r in check.revisits:
        err = truth_error(true, est, r.first_frame, r.last_frame, check.params.gap_m)
        revisits.append({**r.summary(), "truth_error_m": err,
                         "truth_doubled": err is not None and err > TRUTH_TOLERANCE})
    return {"consistent": check.consistent, "seconds": seconds, "revisits": revisits}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cache", required=True, help="experiments.map_merge's --cache folder")
    ap.add_argument("--courses", nargs="+", default=["mars-yard-a", "arroyo-a", "maze"])
    ap.add_argument("--trials", type=int, default=10)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    config = Config()
    cache = Path(args.cache)
    report: dict = {"environment": environment(), "maps": []}
    for course in args.courses:
        jobs = [("A at the true poses", f"{course}-a", None, True),
                ("A", f"{course}-a", None, False)]
        jobs += [(f"B trial {i}", f"{course}-b{i}", 100 + i, False) for i in range(args.trials)]
        for label, name, noise_seed, at_truth in jobs:
            file = cache / f"{name}.npz"
            if not file.is_file():
                raise SystemExit(f"{file}: not found; run experiments.map_merge --cache "
                                 f"{cache} --maps-only first")
            with np.load(file) as data:
                path = None if at_truth else data["path"]
            row = {"course": course, "map": label,
                   **check_map(course, noise_seed, path, config)}
            report["maps"].append(row)
            found = sum(r["doubled"] for r in row["revisits"])
            truth = sum(r["truth_doubled"] for r in row["revisits"])
            print(f"{course:12} {label:20} {len(row['revisits']):3} revisited stretches, "
                  f"{found:3} found doubled, {truth:3} doubled by the truth: "
                  f"{'consistent' if row['consistent'] else 'DOUBLED'} ({row['seconds']:.0f} s)",
                  flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    return report


if __name__ == "__main__":
    main()
