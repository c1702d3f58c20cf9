"""Recovery of known motion-noise parameters by gradient tuning, against a 256-point search.

A simulated course with known true VO alphas (SimInfo.vo_noise); tuning starts 3x off (all
alphas x 3), then reports tuned vs true alphas (target: within 25%) and the RMS of the tuned
parameters vs the best RMS of a Sobol search (target: within 10%). RMS figures are means over
fresh filter keys (``--eval-keys``); the search ranks by the mean over ``--search-keys`` keys.

    python -m experiments.tune_recovery --frames 300 --steps 60 --search 256
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from experiments.common import (
    ALPHAS,
    add_known_noise_arguments,
    key_averaged,
    known_noise_run,
    report,
)
from gslam_jax.config import Config, FilterSection, MapSection, MotionSection
from gslam_jax.driver.machine import environment
from gslam_jax.tuning import designs as D, gradient as TU, space as SP


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_known_noise_arguments(ap)
    ap.add_argument("--objective", default="loglik", choices=TU.TUNE_OBJECTIVES)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--lr", type=float, default=0.05)
    ap.add_argument("--runs", type=int, default=4, help="filter runs per gradient")
    ap.add_argument("--search", type=int, default=256, help="search points (0: skip)")
    ap.add_argument("--search-keys", type=int, default=4,
                    help="filter keys averaged per search point")
    ap.add_argument("--eval-keys", type=int, default=8,
                    help="fresh filter keys averaged for the reported RMS figures")
    args = ap.parse_args(argv)

    run, true = known_noise_run(args)
    start = {k: 3.0 * v for k, v in true.items()}
    config = Config(filter=FilterSection(particles=args.particles, unknown_cells=args.unknown),
                    map=MapSection(margin=2.0), motion=MotionSection(**start))
    t0 = time.perf_counter()
    res = TU.tune(run, config, args.objective, "adam", args.lr, args.steps, names=ALPHAS,
                  runs_per_step=args.runs, key=jax.random.key(1))
    tune_s = time.perf_counter() - t0
    rel = {k: res.values[k] / true[k] - 1.0 for k in ALPHAS}

    averaged = key_averaged(run, config)

    def mean_rms(values: np.ndarray, keys: range) -> np.ndarray:
        return averaged(values, keys, "rms")

    # Fresh keys for the final comparison: a single run's RMS is noisy (0.06 vs 0.19 m at
    # nearby parameters), and the minimum of 256 noisy values is biased low.
    eval_keys = range(1000, 1000 + args.eval_keys)
    row = lambda d: np.array([[d[k] for k in ALPHAS]])  # noqa: E731
    figures = {"course": args.course, "frames": run.num_frames, "particles": args.particles,
               "objective": args.objective, "unknown_cells": args.unknown, "steps": args.steps,
               "true": true, "start": start, "tuned": res.values, "relative_error": rel,
               "tune_seconds": round(tune_s, 1), "eval_keys": args.eval_keys,
               "rms_tuned": float(mean_rms(row(res.values), eval_keys)[0]),
               "rms_true": float(mean_rms(row(true), eval_keys)[0]),
               "rms_start": float(mean_rms(row(start), eval_keys)[0])}
    if args.search:
        space = SP.parse_space({k: {"range": [v / 5.0, v * 5.0], "log": True}
                               for k, v in true.items()})
        values = D.design_points(space, "sobol", args.search)
        t0 = time.perf_counter()
        rms = mean_rms(values, range(args.search_keys))
        best = values[int(np.argmin(rms))]
        figures.update(search_points=args.search, search_keys=args.search_keys,
                       search_seconds=round(time.perf_counter() - t0, 1),
                       search_best=dict(zip(ALPHAS, best.tolist())),
                       rms_search_best_in_search=float(np.min(rms)),
                       rms_search_best=float(mean_rms(best[None], eval_keys)[0]))
        figures["rms_ratio_tuned_to_search"] = figures["rms_tuned"] / figures["rms_search_best"]
    figures["environment"] = environment()
    return report(figures, args.out)


if __name__ == "__main__":
    main()
