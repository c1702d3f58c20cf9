"""Where do the tuning objectives peak? Each alpha scanned at multiples of its true value.

On a simulated course with known VO noise (SimInfo.vo_noise), every alpha in turn is set to
``factor x truth`` (the others at the truth) and the filter's objectives are evaluated by the
batched search, averaged over several keys: the log marginal likelihood estimate (the
``loglik`` objective of ``gslam search`` / ``gslam tune``) and the RMS position error. A
recovery of the true alphas by tuning can only work where the objective peaks at factor 1.

    python -m experiments.objective_scan --white --keys 4
"""

from __future__ import annotations

import argparse

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
from gslam_jax.tuning.evaluation import OBJECTIVES


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_known_noise_arguments(ap)
    ap.add_argument("--beta", type=float, default=0.05, help="beta_prev = beta_new")
    ap.add_argument("--keys", type=int, default=4, help="filter keys averaged per point")
    ap.add_argument("--factors", type=float, nargs="+", default=[0.25, 0.5, 1, 2, 4, 8])
    args = ap.parse_args(argv)

    run, true = known_noise_run(args)
    config = Config(filter=FilterSection(particles=args.particles, unknown_cells=args.unknown,
                                         beta_prev=args.beta, beta_new=args.beta),
                    map=MapSection(margin=2.0), motion=MotionSection(**true))
    factors = np.asarray(args.factors, np.float64)
    scans: dict[str, dict[str, list[float]]] = {}
    for name in ALPHAS:
        averaged = key_averaged(run, config, (name,))
        values = (true[name] * factors)[:, None]
        scans[name] = {}
        for objective in OBJECTIVES:
            scans[name][objective] = averaged(values, range(args.keys), objective).round(4).tolist()
            best = factors[np.argmax(scans[name][objective]) if objective == "loglik"
                           else np.argmin(scans[name][objective])]
            print(f"{name:14s} {objective:7s} best at {best:g} x truth: "
                  f"{scans[name][objective]}", flush=True)
    figures = {"course": args.course, "frames": run.num_frames, "particles": args.particles,
               "unknown_cells": args.unknown, "beta": args.beta, "white": args.white,
               "keys": args.keys, "true": true, "factors": factors.tolist(), "scans": scans,
               "environment": environment()}
    return report(figures, args.out)


if __name__ == "__main__":
    main()
