"""Does the result depend on the map frame's orientation? A KITTI sequence built again in
frames turned about its start, with local maps on the robot's lattice or the map's
(``[localmap] lattice``), and the filter run over several seeds in each.

    python -m experiments.frame_lattice --kitti ../shared/data/kitti-stereo-51 --sequence seq1 \
        --turns 0 11.25 22.5 45 67.5 90 --seeds 0 1 2 3 4 5 6 7 --cache /tmp/frame_lattice

Turning the frame turns the map's lattice against the terrain and, with robot-lattice local
maps, against every local map: each local cell then takes the map cell its centre falls in, two
local cells share some map cells and other map cells stay empty (docs/notebook/results.md, "The map
frame's orientation"). With map-lattice local maps the points are binned on the map's axes at
the VO pose, so only the particle's heading correction turns them against the map. The Runs
are built by the front-end in each frame (``kitti_frontend(frame_turn=...)``), so the ground
truth and start pose turn with the frame and the local maps are binned for it; they are cached
per lattice and angle in ``--cache``.

Each line: lattice, angle, per seed RMS against VO-only's (after the rigid fit), the final
drift (% of the true distance), and the rigid fit's turn of the path against the truth's minus
the VO's (a heading bias that the frame sets shows here); then the means, and how many seeds
drift less than VO.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from gslam_jax.config import apply_overrides, layered_config
from gslam_jax.sim.courses import COURSES
from gslam_jax.datasets.kitti import KittiParams, kitti_frontend
from gslam_jax.run import load_run, save_run
from gslam_jax.vo.localmap import localmap_params

from experiments.common import print_header
from experiments.proposal_compare import case_row


def build(kitti: Path, sequence: str | None, config, lattice: str, turn_deg: float,
          cache: Path | None):
    """The sequence's Run in a frame turned by ``turn_deg``, local maps on ``lattice``."""
    path = None if cache is None else cache / f"{lattice}_{turn_deg:g}.npz"
    if path is not None and path.exists():
        return load_run(path)
    cfg = apply_overrides(config, [f"localmap.lattice={lattice}"])
    fe = KittiParams().frontend
    params = KittiParams(sequence=sequence,
                         frontend=dataclasses.replace(fe, local_map=localmap_params(cfg)))
    run = kitti_frontend(kitti, params, frame_turn=math.radians(turn_deg)).run
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        save_run(path, run)
    return run


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kitti", type=Path, required=True, help="KITTI odometry folder")
    ap.add_argument("--sequence")
    ap.add_argument("--turns", type=float, nargs="+", default=[0.0, 22.5, 45.0, 67.5, 90.0],
                    metavar="DEG")
    ap.add_argument("--lattices", nargs="+", default=["robot", "map"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    ap.add_argument("--config", type=Path)
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--cache", type=Path, help="folder for the Runs built (reused)")
    ap.add_argument("--json", type=Path, help="also write every row here (JSON lines)")
    args = ap.parse_args(argv)
    print_header(args.set)
    config = layered_config(args.config, None, args.set, courses=COURSES)
    out = args.json.open("w") if args.json else None
    for lattice in args.lattices:
        for turn in args.turns:
            run = build(args.kitti, args.sequence, config, lattice, turn, args.cache)
            rows = [case_row(f"{lattice}@{turn:g}", run, config, 1.0, "motion", s)
                    for s in args.seeds]
            ratio = np.array([r["ratio"] for r in rows])
            drift = np.array([r["slam_drift_pct"] for r in rows])
            bias = np.array([r["slam_fit_turn_deg"] - r["vo_fit_turn_deg"] for r in rows])
            vo_drift = rows[0]["vo_drift_pct"]
            print(f"{lattice:>5} {turn:6.2f} deg: RMS/VO "
                  + " ".join(f"{x:.2f}" for x in ratio)
                  + f" | mean {ratio.mean():.2f}x, drift {drift.mean():.2f} % (VO {vo_drift:.2f}"
                  f" %, under it {int(np.sum(drift < vo_drift))}/{len(rows)}), path turn "
                  f"against VO's {bias.mean():+.2f} deg (sd {bias.std():.2f})", flush=True)
            if out:
                for r in rows:
                    out.write(json.dumps({"lattice": lattice, "turn_deg": turn, **r}) + "\n")
                out.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
