"""Motion noise without ground truth: fit the alphas of eqs. 2-3 to the filter's own path.

A user without ground truth cannot run ``gslam fit-motion``, and the marginal likelihood over
the alphas is nearly flat on short logs (docs/notebook/real-data.md). This measures the obvious
substitute, a hard-EM iteration: run the filter with the noise it is given, take its reported
path as the reference, fit the alphas to the VO's increments against that path with the same
maximum-likelihood fit as ``gslam fit-motion`` (``tuning.motion_fit.fit_motion``, the VO errors
summed over the frames between local maps), and run again with them. The reference is the
filter's point estimate, not its posterior, so each iteration also drops the path's own
uncertainty from the fit: the alphas can only shrink towards what the path explains.

    python -m experiments.self_calibration --courses mars-yard-a arroyo-a maze --sim-seeds 0 1 \
        --noise-scale 10 --iterations 2 --config configs/table1.toml --max-frames 600

Each line: the case, the iteration (0: the given noise), the alphas run with, the RMS after
the rigid fit against the ground truth (which the iterations never see) and its ratio to the
calibrated run (the config's own alphas, run once per case first). The alphas fitted to the
ground truth itself (``fit_run``), and the RMS with them, are printed per case for reference.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from gslam_jax.config import Config
from gslam_jax.driver import slam
from gslam_jax.evaluation import metrics
from gslam_jax.run import Run
from gslam_jax.tuning.motion_fit import ALPHA_THETA_MAX, fit_run

from experiments.common import (add_case_arguments, alphas_of, cases_from_arguments,
                                print_header, with_alphas)

# a heading-per-turn alpha of exactly 0 would make a turn in place noiseless
MIN_ALPHA_THETA = 1e-4


def self_fit(run: Run, path: np.ndarray) -> tuple[float, float, float]:
    """The alphas fitted to ``run``'s VO against ``path`` in place of the ground truth."""
    fit = fit_run(run._replace(ground_truth=np.asarray(path, np.float64)))
    return (fit.alpha_d, fit.alpha_theta_d,
            float(np.clip(fit.alpha_theta, MIN_ALPHA_THETA, ALPHA_THETA_MAX)))


def rms(run: Run, config: Config, reference: str = "reported") -> tuple[float, np.ndarray]:
    """The filter's RMS against the ground truth (after the rigid fit) of its reported path,
    and the path to fit the next alphas to: the reported one (``[filter] estimate``), or with
    ``reference = "best"`` the final best particle's path through its ancestry (one path of
    the posterior, with its own noise, where the smoother's paths average the particles' noise
    out)."""
    res = slam.run_slam(run, config)
    err = metrics.errors_over_known_frames({"slam": res.path}, run.ground_truth)
    return err["slam_rms_m"], res.best_path if reference == "best" else res.path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_case_arguments(ap)
    ap.add_argument("--noise-scale", type=float, nargs="+", default=[10.0],
                    help="the given noise: the config's alphas times this")
    ap.add_argument("--iterations", type=int, default=2)
    ap.add_argument("--reference", choices=("reported", "best"), default="reported",
                    help="the path the alphas are fitted to: the reported one ([filter] "
                    "estimate), or the final best particle's")
    ap.add_argument("--json", type=Path, help="also write every row here (JSON lines)")
    args = ap.parse_args()
    print_header(args.set)
    out = args.json.open("w") if args.json else None
    for name, run, config in cases_from_arguments(args):
        calibrated, _ = rms(run, config)
        truth_alphas = self_fit(run, run.ground_truth)
        truth_rms, _ = rms(run, with_alphas(config, truth_alphas))
        print(f"{name}: calibrated alphas {alphas_of(config)} RMS {calibrated:.3f}; fitted to "
              f"the ground truth {truth_alphas[0]:.4f} {truth_alphas[1]:.4f} "
              f"{truth_alphas[2]:.4f} RMS {truth_rms:.3f} ({truth_rms / calibrated:.2f}x)",
              flush=True)
        for scale in args.noise_scale:
            alphas = tuple(a * scale for a in alphas_of(config))
            for it in range(args.iterations + 1):
                value, path = rms(run, with_alphas(config, alphas), args.reference)
                row = {"source": name, "noise_scale": scale, "iteration": it,
                       "reference": args.reference,
                       "alphas": alphas, "slam_rms_m": value, "calibrated_rms_m": calibrated,
                       "ratio": value / calibrated}
                print(f"  x{scale:g} iteration {it}: alphas {alphas[0]:.4f} {alphas[1]:.4f} "
                      f"{alphas[2]:.4f} RMS {value:.3f} ({row['ratio']:.2f}x calibrated)",
                      flush=True)
                if out:
                    out.write(json.dumps(row) + "\n")
                    out.flush()
                alphas = self_fit(run, path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
