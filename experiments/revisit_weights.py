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
(docs/notebook/results.md, "How long a loop closes").

``--at-truth M`` measures instead, with no filter, why: the local maps of the first M metres
fused at the true poses (eq. 14), and every later local map from 40 m before the revisit scored
against that map cell by cell, at its true pose and 1 m to its left, as a log-likelihood ratio
against chance (the filter's eq. 26, ``cells.log_predictive_integer``, minus its mean over 64
random known cells), per band of range; without and with ``[filter] range_noise = "profile"``
(``observations.run_range_noise``: the map cell's S' gets k' n(r)).
"""

from __future__ import annotations

import argparse
import json
import tempfile
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from scipy.stats import spearmanr

from experiments.loop_paths import START_M, circle_file
from gslam_jax.config import apply_overrides, layered_config
from gslam_jax.sim.courses import COURSES
from gslam_jax.datasets.sim_path import simulate_path
from gslam_jax.driver import slam
from gslam_jax.driver.machine import environment
from gslam_jax.driver.observations import run_range_noise
from gslam_jax.evaluation import loops
from gslam_jax.gridmap.grid import arc_length
from gslam_jax.gridmap.pose_maps import local_cell_centres, place_local_map, pose_lattice
from gslam_jax.rbpf import cells
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
    arc = arc_length(truth)
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


def truth_scores(run, config, revisit: loops.Revisit, map_m: float, bands=(0, 4, 7, 11),
                 chance_cells: int = 64) -> list[dict]:
    """Per local map from 40 m of travel before the revisit to the end: the log-likelihood
    ratio against chance of its cells on the map of the first ``map_m`` metres, at the true
    pose (per cell, by range band, and summed) and summed 1 m to the left, without and with
    the range profile. See the module docstring."""
    truth = run.ground_truth
    arc = arc_length(truth)
    L = run.local_maps.shape[1]
    noise = run_range_noise(run, config).reshape(L, L)
    lattice = pose_lattice(run, truth, 2.0)
    K, S = np.zeros(lattice.k.size), np.zeros(lattice.k.size)
    frames = np.flatnonzero(run.obs_index >= 0)
    for t in frames[arc[frames] < map_m]:
        flat, k, s = place_local_map(run, t, truth[t], lattice)
        np.add.at(K, flat, k)
        np.add.at(S, flat, s)
    known = np.flatnonzero(K > 0)
    chance = np.random.default_rng(0).choice(known, chance_cells)
    log_predictive = jax.jit(cells.log_predictive_integer)
    rng = np.hypot(*local_cell_centres(L, float(run.resolution)))

    def lr(t, pose, with_noise):
        flat, k, s = place_local_map(run, t, pose, lattice)
        seen = cells.obs_from_stats(run.local_maps[run.obs_index[t]])[..., 0] > 0  # as placed
        n = noise[seen] if with_noise else np.zeros(int(seen.sum()))
        on = K[flat] > 0
        k, s, n, r = k[on], s[on], n[on], rng[seen][on]

        def eq26(kp, Sp):
            """The filter's float32 eq. 26 of these cells against map cells (k', S' + k' n),
            padded to L * L cells so that one compilation serves every local map."""
            kp, Sp = np.broadcast_arrays(kp, Sp + kp * n)
            pad = [(0, 0)] * (kp.ndim - 1) + [(0, L * L - k.size)]
            one = partial(np.pad, pad_width=pad, constant_values=1.0)
            out = log_predictive(*(jnp.float32(one(np.broadcast_to(x, kp.shape)))
                                   for x in (k, s, kp, Sp)))
            return np.asarray(out)[..., :k.size]

        lam = eq26(K[flat][on], S[flat][on])
        base = eq26(K[chance][:, None], S[chance][:, None]).mean(axis=0)  # [chance, cells]
        return lam - base, r

    rows = []
    for t in frames[(arc[frames] > arc[revisit.j] - 40.0)]:
        pose = truth[t]
        left = pose + np.array([-np.sin(pose[2]), np.cos(pose[2]), 0.0])
        row = {"frame": int(t), "travel_m": float(arc[t])}
        for name, with_noise in (("none", False), ("profile", True)):
            g, r = lr(t, pose, with_noise)
            g_left, _ = lr(t, left, with_noise)
            row[name] = {"cells": int(g.size), "total": float(g.sum()),
                         "total_1m_left": float(g_left.sum()),
                         "per_cell_by_band": [float(g[(r >= a) & (r < b)].mean())
                                              if np.any((r >= a) & (r < b)) else None
                                              for a, b in zip(bands[:-1], bands[1:])]}
        rows.append(row)
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
    ap.add_argument("--at-truth", type=float, metavar="M",
                    help="no filter: score later local maps at the truth against the map of "
                         "the first M metres (see the module docstring)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)

    folder = Path(tempfile.mkdtemp())
    loop_file = circle_file(folder, args.circle, 20.0)
    config = layered_config(args.config, args.course, args.set, courses=COURSES)
    config = apply_overrides(config, [f"map.margin={max(config.map.margin, 0.1 * args.circle):g}"])
    print(environment())
    out = []
    for seed in args.seeds:
        run, _ = simulate_path(loop_file, seed=seed, course=args.course,
                               params=localmap_params(config))
        revisit = loops.find_revisit(run.ground_truth, START_M, 0.5 * args.circle)
        if revisit is None:
            raise SystemExit(f"seed {seed}: the driven circle has no revisit within 2 m")
        if args.at_truth is not None:
            rows = truth_scores(run, config, revisit, args.at_truth)
            print(f"seed {seed}: local maps scored at the truth against the map of the first "
                  f"{args.at_truth:g} m (log-likelihood ratio against chance)")
            print("  travel   cells | none: per cell 0-4/4-7/7-11 m   total  1 m left | "
                  "profile: per cell 0-4/4-7/7-11 m   total  1 m left")
            fmt = lambda v: "   -  " if v is None else f"{v:+6.2f}"  # noqa: E731
            for r in rows[::3]:
                a, b = r["none"], r["profile"]
                print(f"  {r['travel_m']:6.1f}  {a['cells']:5d} | "
                      f"{' '.join(fmt(v) for v in a['per_cell_by_band'])} "
                      f"{a['total']:+8.0f} {a['total_1m_left']:+8.0f} | "
                      f"{' '.join(fmt(v) for v in b['per_cell_by_band'])} "
                      f"{b['total']:+8.0f} {b['total_1m_left']:+8.0f}")
            out.append({"seed": seed, "revisit": list(revisit), "at_truth": rows})
            continue
        cfg = apply_overrides(config, [f"filter.particles={args.particles}",
                                       f"filter.seed={seed}", "filter.resample_ratio=0",
                                       "filter.tempering=fixed"])
        poses, log_w = [], []

        def keep(report):
            poses.append(np.asarray(report.info.pose))
            log_w.append(np.asarray(report.info.log_w))

        slam.run_slam(run, cfg, on_chunk=keep)
        arc = arc_length(run.ground_truth)
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
