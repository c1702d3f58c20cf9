"""Where do the tuning objectives peak? Each alpha scanned at multiples of its true value.

On a simulated course with known VO noise (SimInfo.vo_noise), every alpha in turn is set to
``factor x truth`` (the others at the truth) and the filter's objectives are evaluated by the
batched search, averaged over several keys: the log marginal likelihood estimate (the
``loglik`` objective of ``gslam search`` / ``gslam tune``) and the RMS position error. A
recovery of the true alphas by tuning can only work where the objective peaks at factor 1.

    python experiments/objective_scan.py --white --keys 4
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gslam_jax import search as S  # noqa: E402
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
    ap.add_argument("--unknown", default="ignore", choices=("ignore", "sample"))
    ap.add_argument("--beta", type=float, default=0.05, help="beta_prev = beta_new")
    ap.add_argument("--keys", type=int, default=4, help="filter keys averaged per point")
    ap.add_argument("--factors", type=float, nargs="+", default=[0.25, 0.5, 1, 2, 4, 8])
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
    config = Config(filter=FilterSection(particles=args.particles, unknown_cells=args.unknown,
                                         beta_prev=args.beta, beta_new=args.beta),
                    map=MapSection(margin=2.0), motion=MotionSection(**true))
    factors = np.asarray(args.factors, np.float64)
    scans: dict[str, dict[str, list[float]]] = {}
    for name in ALPHAS:
        space = S.parse_space({name: [float(factors.min() * true[name]),
                                      float(factors.max() * true[name])]})
        values = (true[name] * factors)[:, None]
        scans[name] = {}
        for objective in S.OBJECTIVES:
            per_key = []
            for k in range(args.keys):
                res = S.search(run, config, space, values=values, objective=objective,
                               key=jax.random.key(k))
                per_key.append(res.objective[np.argsort(res.values[:, 0])])
            scans[name][objective] = np.mean(per_key, axis=0).round(4).tolist()
            best = factors[np.argmax(scans[name][objective]) if objective == "loglik"
                           else np.argmin(scans[name][objective])]
            print(f"{name:14s} {objective:7s} best at {best:g} x truth: "
                  f"{scans[name][objective]}", flush=True)
    figures = {"course": args.course, "frames": run.num_frames, "particles": args.particles,
               "unknown_cells": args.unknown, "beta": args.beta, "white": args.white,
               "keys": args.keys, "true": true, "factors": factors.tolist(), "scans": scans,
               "environment": environment()}
    print(json.dumps(figures, indent=2))
    if args.out:
        Path(args.out).write_text(json.dumps(figures, indent=2))
    return figures


if __name__ == "__main__":
    main()
