"""Recovery of known motion-noise parameters by gradient tuning, against a 256-point search.

A simulated course with known true VO alphas (SimInfo.vo_noise); tuning starts 3x off (all
alphas x 3), then reports tuned vs true alphas (target: within 25%) and the RMS of the tuned
parameters vs the best RMS of a Sobol search (target: within 10%).

    python experiments/tune_recovery.py --frames 300 --steps 60 --search 256
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gslam_jax import search as S  # noqa: E402
from gslam_jax import tuning as TU  # noqa: E402
from gslam_jax.bench import environment  # noqa: E402
from gslam_jax.config import Config, FilterSection, MapSection, MotionSection  # noqa: E402
from gslam_jax.datasets.sim import simulate_run  # noqa: E402
from gslam_jax.localmap import LocalMapParams  # noqa: E402
from gslam_jax.sim.vonoise import VO_PROFILES  # noqa: E402

ALPHAS = ("alpha_d", "alpha_theta_d", "alpha_theta")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--course", default="mars-yard-a")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--particles", type=int, default=64)
    ap.add_argument("--objective", default="loglik", choices=TU.TUNE_OBJECTIVES)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--lr", type=float, default=0.05)
    ap.add_argument("--runs", type=int, default=4, help="filter runs per gradient")
    ap.add_argument("--search", type=int, default=256, help="search points (0: skip)")
    ap.add_argument("--white", action="store_true",
                    help="VO noise of eqs. 1-3 only (no bias, no failures): the model is exact")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)

    lm = LocalMapParams(resolution=0.16, max_range=2.5, travel=1.0, cells=32)
    vo = VO_PROFILES[args.course]
    if args.white:
        vo = dataclasses.replace(vo, scale_bias_std=0.0, heading_bias_std=0.0, failure_rate=0.0)
    run, info = simulate_run(args.course, 0, lm, max_frames=args.frames, vo_noise=vo)
    true = {k: getattr(info.vo_noise, k) for k in ALPHAS}
    start = {k: 3.0 * v for k, v in true.items()}
    config = Config(filter=FilterSection(particles=args.particles, unknown_cells="ignore"),
                    map=MapSection(margin=2.0), motion=MotionSection(**start))
    t0 = time.perf_counter()
    res = TU.tune(run, config, args.objective, "adam", args.lr, args.steps, names=ALPHAS,
                  runs_per_step=args.runs, key=jax.random.key(1))
    tune_s = time.perf_counter() - t0
    rel = {k: res.values[k] / true[k] - 1.0 for k in ALPHAS}

    def rms_of(values: dict) -> float:
        space = S.parse_space({k: [0.5 * v, 2.0 * v] for k, v in values.items()})
        r = S.search(run, config, space, values=np.array([[values[k] for k in space.names]]),
                     objective="rms")
        return float(r.objective[0])

    figures = {"course": args.course, "frames": run.num_frames, "particles": args.particles,
               "objective": args.objective, "steps": args.steps, "true": true, "start": start,
               "tuned": res.values, "relative_error": rel, "tune_seconds": round(tune_s, 1),
               "rms_tuned": rms_of(res.values), "rms_true": rms_of(true),
               "rms_start": rms_of(start)}
    if args.search:
        space = S.parse_space({k: {"range": [v / 5.0, v * 5.0], "log": True}
                               for k, v in true.items()})
        t0 = time.perf_counter()
        sr = S.search(run, config, space, "sobol", args.search, "rms")
        figures.update(search_seconds=round(time.perf_counter() - t0, 1),
                       rms_search_best=float(sr.objective[0]), search_best=sr.best())
        figures["rms_ratio_tuned_to_search"] = figures["rms_tuned"] / figures["rms_search_best"]
    figures["environment"] = environment()
    print(json.dumps(figures, indent=2, default=float))
    if args.out:
        Path(args.out).write_text(json.dumps(figures, indent=2, default=float))
    return figures


if __name__ == "__main__":
    main()
