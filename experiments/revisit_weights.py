"""Which hypotheses the weights favour on the way into a loop's revisit.

    python -m experiments.revisit_weights --config configs/table1.toml --circle 100 \
        --particles 200 --seeds 0 1 2

Drives a circle (``experiments.loop_closure``) and runs the filter with resampling off and the
paper's fixed tempering, so that the J particles are J independent hypotheses, each with the
map of its own path, and each keeps the weight the likelihood gives it. For every window of
``--window`` metres of travel it reports, over the particles:

- rho: Spearman's rank correlation of the window's log-weight increments with each particle's
  revisit error (``loops.revisit_error`` at the loop's revisit): negative when the window's data
  favour the hypotheses that will close the loop, positive when they favour those that will not;
- the particles' mean pose error at the window's end (forward, left in the true robot frame, and
  heading), unweighted and weighted by the window's increments, and those weights' ESS.

This is the measurement behind "more particles close the 100 m Mars Yard circle less often"
(docs/results.md, "How long a loop closes").
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

from experiments.loop_closure import START_M, circle_file
from gslam_jax import loops, slam
from gslam_jax.config import apply_overrides, layered_config
from gslam_jax.datasets.sim_path import simulate_path
from gslam_jax.machine import environment
from gslam_jax.vo.localmap import localmap_params


def pose_errors(poses: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """[J, 3] errors of particle poses [J, 3] against one true pose [3]: forward and left in
    the true robot frame (m), heading (rad, wrapped)."""
    d = poses[:, :2] - truth[:2]
    c, s = np.cos(truth[2]), np.sin(truth[2])
    heading = np.angle(np.exp(1j * (poses[:, 2] - truth[2])))
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], heading], axis=1)


def window_rows(P: np.ndarray, log_w: np.ndarray, truth: np.ndarray, revisit: loops.Revisit,
                window: float, from_m: float) -> list[dict]:
    """One row per window of travel from ``from_m`` to the end: see the module docstring.
    P: [T, J, 3] particle poses; log_w: [T, J] log weights (no resampling)."""
    J = P.shape[1]
    err = np.array([loops.revisit_error(truth, P[:, p], revisit.i, revisit.j) for p in range(J)])
    arc = loops.arc_length(truth)
    rows = []
    for m in np.arange(from_m, arc[-1] - window + 1e-9, window):
        a, b = (min(int(np.searchsorted(arc, x)), len(arc) - 1) for x in (m, m + window))
        inc = log_w[b] - log_w[a]
        w = np.exp(inc - inc.max())
        w /= w.sum()
        e = pose_errors(P[b], truth[b])
        rows.append({"from_m": float(m), "to_m": float(m + window),
                     "rho": float(spearmanr(inc, err)[0]),
                     "mean_error": [float(x) for x in e.mean(axis=0)],
                     "weighted_error": [float(x) for x in w @ e], "ess": float(1 / np.sum(w**2))})
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--circle", type=float, default=100.0, help="perimeter, m")
    ap.add_argument("--particles", type=int, default=200)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--course", default="mars-yard-a", help="world kind and VO noise")
    ap.add_argument("--config", type=Path)
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--window", type=float, default=5.0, help="metres of travel per window")
    ap.add_argument("--from-m", type=float, default=None,
                    help="first window's start (default: 40 m before the revisit)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)

    folder = Path(tempfile.mkdtemp())
    loop_file = circle_file(folder, args.circle, 20.0)
    config = layered_config(args.config, args.course, args.set)
    config = apply_overrides(config, [f"map.margin={max(config.map.margin, 0.1 * args.circle):g}"])
    print(environment())
    out = []
    for seed in args.seeds:
        run, _ = simulate_path(loop_file, seed=seed, course=args.course,
                               params=localmap_params(config))
        revisit = loops.find_revisit(run.ground_truth, START_M, 0.5 * args.circle)
        if revisit is None:
            raise SystemExit(f"seed {seed}: the driven circle has no revisit within 2 m")
        cfg = apply_overrides(config, [f"filter.particles={args.particles}",
                                       f"filter.seed={seed}", "filter.resample_ratio=0",
                                       "filter.tempering=fixed"])
        poses, log_w = [], []

        def keep(report):
            poses.append(np.asarray(report.info.pose))
            log_w.append(np.asarray(report.info.log_w))

        slam.run_slam(run, cfg, on_chunk=keep)
        arc = loops.arc_length(run.ground_truth)
        start = arc[revisit.j] - 40.0 if args.from_m is None else args.from_m
        rows = window_rows(np.concatenate(poses), np.concatenate(log_w), run.ground_truth,
                           revisit, args.window, max(0.0, start))
        print(f"seed {seed}: revisit frames {revisit.i}, {revisit.j} at {arc[revisit.j]:.0f} m "
              f"of travel")
        print("  window (m)    rho   mean error fwd/left/deg     weighted fwd/left/deg    ESS")
        for r in rows:
            me, we = r["mean_error"], r["weighted_error"]
            print(f"  {r['from_m']:5.0f}-{r['to_m']:<5.0f} {r['rho']:+.2f}   "
                  f"{me[0]:+6.2f} {me[1]:+6.2f} {np.degrees(me[2]):+6.1f}      "
                  f"{we[0]:+6.2f} {we[1]:+6.2f} {np.degrees(we[2]):+6.1f}   {r['ess']:6.1f}")
        out.append({"seed": seed, "revisit": list(revisit), "windows": rows})
    if args.json:
        args.json.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()},
                                         "runs": out}, indent=1))


if __name__ == "__main__":
    main()
