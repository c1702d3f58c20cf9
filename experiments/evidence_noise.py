"""The motion noise fitted by the filter's own evidence (``tuning.evidence_fit``; ``gslam
fit-motion --evidence``), no ground truth: the alphas as given (scaled from their calibrated
value by ``--noise-scale``), the factor the evidence ladder chooses, and the filter's RMS with
the given and with the fitted alphas, against the calibrated run.

    python -m experiments.evidence_noise --courses mars-yard-a arroyo-a maze --sim-seeds 0 1 2 \
        --noise-scale 10 0.3 --config configs/table1.toml --max-frames 600
    python -m experiments.evidence_noise --runs /tmp/kitti51.npz --seeds 0 1 2 3 4 5 6 7

Each line: case, noise scale, the evidence per factor, the chosen factor (as a multiple of the
calibrated alphas), then per filter seed the RMS with the given alphas, with the fitted ones
and with the calibrated ones (noise scale 1), and the fitted run's ratio to the calibrated.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from gslam_jax.tuning.evidence_fit import DEFAULT_FACTORS, DEFAULT_SEEDS, fit_noise_scale

from experiments.common import (add_case_arguments, cases_from_arguments, print_header,
                                scaled_alphas)
from experiments.proposal_compare import case_row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_case_arguments(ap)
    ap.add_argument("--noise-scale", type=float, nargs="+", default=[1.0],
                    help="the given alphas as multiples of the config's (calibrated) ones")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0], help="filter seeds")
    ap.add_argument("--factors", type=float, nargs="+", default=list(DEFAULT_FACTORS),
                    help="the ladder, multiples of the given alphas")
    ap.add_argument("--evidence-seeds", type=int, nargs="+", default=list(DEFAULT_SEEDS),
                    help="filter seeds the evidence is averaged over")
    ap.add_argument("--proposal", default="motion")
    ap.add_argument("--json", type=Path, help="also write every row here (JSON lines)")
    args = ap.parse_args()
    print_header(args.set)
    out = args.json.open("w") if args.json else None
    for name, run, config in cases_from_arguments(args):
        rows: dict[tuple[float, int], dict] = {}

        def row(scale: float, seed: int) -> dict:
            if (scale, seed) not in rows:  # each run once (a fit may land on a given scale)
                rows[scale, seed] = case_row(name, run, config, scale, args.proposal, seed)
            return rows[scale, seed]

        calibrated = {s: row(1.0, s)["slam_rms_m"] for s in args.seeds}
        for scale in args.noise_scale:
            given = scaled_alphas(config, scale)
            fit = fit_noise_scale(run, given, args.factors, args.evidence_seeds)
            total = scale * fit.factor
            ladder = " ".join(f"{f:g}:{e:.0f}" for f, e in zip(fit.factors, fit.log_evidence))
            print(f"{name} x{scale:g}: evidence {ladder} -> x{fit.factor:g} of given = "
                  f"x{total:.3g} of calibrated{' (ladder edge)' if fit.on_edge else ''}",
                  flush=True)
            for s in args.seeds:
                before, after = row(scale, s), row(total, s)
                ratio = after["slam_rms_m"] / calibrated[s]
                print(f"   seed {s}: VO {before['vo_rms_m']:.3f} given {before['slam_rms_m']:.3f}"
                      f" fitted {after['slam_rms_m']:.3f} calibrated {calibrated[s]:.3f} "
                      f"({ratio:.2f}x) drift given {before['slam_drift_pct']:.2f} % fitted "
                      f"{after['slam_drift_pct']:.2f} % VO {after['vo_drift_pct']:.2f} %",
                      flush=True)
                if out:
                    out.write(json.dumps({
                        "source": name, "noise_scale": scale, "factor": fit.factor,
                        "fitted_scale": total, "on_edge": fit.on_edge,
                        "factors": fit.factors.tolist(),
                        "log_evidence": np.asarray(fit.log_evidence).tolist(), "seed": s,
                        "vo_rms_m": before["vo_rms_m"], "given_rms_m": before["slam_rms_m"],
                        "fitted_rms_m": after["slam_rms_m"], "calibrated_rms_m": calibrated[s],
                        "given_drift_pct": before["slam_drift_pct"],
                        "fitted_drift_pct": after["slam_drift_pct"],
                        "vo_drift_pct": after["vo_drift_pct"]}) + "\n")
                    out.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
