"""Time to good parameters: search strategies against a 256-point Sobol search.

For each problem (two simulated course prefixes and the real KITTI frames of a Run file) and
each space (4 and 8 parameters), every strategy runs with the same batched evaluator (the
mean-path RMS after the rigid fit, averaged over ``--select-keys`` filter keys, sets vmapped /
sharded in batches of ``--batch`` by ``evaluation.evaluate``, compiled before any clock starts):

* sobol: 256 scrambled Sobol points (the reference), halton: ``--halton`` Halton points;
* tpe: Optuna TPE asking ``--batch`` sets per evaluator call, ``--tpe`` sets in all;
* halving: ``--halving`` Sobol points on the first third of the frames, the best third of them
  on all frames;
* gradient: ``tuning.tune`` (supervised, adam) from the config's values, ``--steps`` steps of
  ``--runs`` filter runs (the 8-parameter space tunes 7: min_points has no gradient).

Each strategy's incumbents (its best set after every call; the gradient's current values every
``--every`` steps) are then re-scored on ``--fresh-keys`` keys not used for selection. The
target is 1.05 x the fresh-key RMS of the Sobol-256 search's best set; the time to the target
is the wall time at the first incumbent whose fresh-key RMS is within it.

    nice -n 5 python -m experiments.search_strategies --kitti /tmp/kitti51.npz --out s.json

(the Run file from ``gslam run --source kitti --path ../shared/data/kitti-stereo-51
--save-run /tmp/kitti51.npz``).
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import jax
import numpy as np

from experiments.common import report  # noqa: E402
from gslam_jax.app.bench import environment  # noqa: E402
from gslam_jax.config import Config, FilterSection, MapSection  # noqa: E402
from gslam_jax.datasets.sim import simulate_run  # noqa: E402
from gslam_jax.driver import device_arrays, sizing  # noqa: E402
from gslam_jax.run import Run, load_run  # noqa: E402
from gslam_jax.tuning import designs as D  # noqa: E402
from gslam_jax.tuning import evaluation as E  # noqa: E402
from gslam_jax.tuning import gradient as TU  # noqa: E402
from gslam_jax.tuning import space as SP  # noqa: E402
from gslam_jax.tuning import strategies as ST  # noqa: E402
from gslam_jax.vo.localmap import LocalMapParams  # noqa: E402

LOG = lambda lo, hi: {"range": [lo, hi], "log": True}  # noqa: E731
SPACES = {
    "4": {"alpha_d": LOG(0.005, 0.5), "alpha_theta_d": LOG(0.001, 0.1),
          "alpha_theta": LOG(0.005, 0.5), "beta_new": LOG(0.01, 1.0)},
    "8": {"alpha_d": LOG(0.005, 0.5), "alpha_theta_d": LOG(0.001, 0.1),
          "alpha_theta": LOG(0.005, 0.5), "beta_prev": LOG(0.01, 1.0),
          "beta_new": LOG(0.01, 1.0), "min_variance": LOG(1e-6, 1e-2),
          "obs_weight": LOG(0.1, 1.0), "min_points": [2.0, 6.0]},
}


def prefix_run(run: Run, frames: int) -> Run:
    """The first ``frames`` frames of ``run`` (and the local maps they use)."""
    idx = run.obs_index[:frames]
    m = int(idx.max()) + 1 if np.any(idx >= 0) else 0
    cut = lambda a: None if a is None else a[:frames]  # noqa: E731
    return run._replace(controls=run.controls[:frames], obs_index=idx,
                        local_maps=run.local_maps[:max(m, 1)], timestamps=run.timestamps[:frames],
                        ground_truth=cut(run.ground_truth), vo_failed=cut(run.vo_failed),
                        lattice_headings=(None if run.lattice_headings is None
                                          else run.lattice_headings[:max(m, 1)]))


def evaluator(run: Run, config: Config, names: tuple[str, ...], keys: list[int], batch: int
              ) -> ST.Evaluator:
    """values [P, d] -> mean-path RMS [P] averaged over ``keys``; P padded to a multiple of
    ``batch`` so that every call reuses one compiled shape."""
    inputs, cfg = device_arrays.run_arrays(run, config)
    base = sizing.filter_params(config)

    def per_key(values: np.ndarray) -> np.ndarray:
        P = len(values)
        pad = (-P) % batch
        v = np.concatenate([values, np.repeat(values[-1:], pad, 0)]) if pad else values
        return np.stack([E.evaluate(v, jax.random.key(k), inputs, base, names, cfg, "rms",
                                    batch=batch)[:P] for k in keys])

    def f(values: np.ndarray) -> np.ndarray:
        return per_key(values).mean(axis=0)

    f.per_key = per_key  # [K, P]: the fresh-key spread
    return f


def gradient_trace(run: Run, config: Config, names: tuple[str, ...], steps: int, runs: int,
                   lr: float, every: int) -> ST.Trace:
    """Supervised adam tuning; incumbent = the current values every ``every`` steps. One step
    is run first to compile (not timed)."""
    tunable = tuple(n for n in names if n in SP.TUNABLE_NAMES)
    TU.tune(run, config, "supervised", "adam", lr, 1, names=tunable, runs_per_step=runs,
            key=jax.random.key(99))
    trace = ST.Trace([], [], [], [])
    fixed = {n: SP.base_values(config)[n] for n in names}
    t0 = time.perf_counter()

    def on_step(step: int, loss: float, values: dict[str, float]) -> None:
        if step % every == 0 or step == steps:
            trace.seconds.append(time.perf_counter() - t0)
            trace.incumbents.append(np.array([{**fixed, **values}[n] for n in names]))
            trace.scores.append(loss)
            trace.evaluated.append(step * runs)

    TU.tune(run, config, "supervised", "adam", lr, steps, names=tunable, runs_per_step=runs,
            key=jax.random.key(0), on_step=on_step)
    return trace


def time_to_band(trace: ST.Trace, fresh: list[float], target: float) -> float | None:
    for t, f in zip(trace.seconds, fresh):
        if f <= target:
            return t
    return None


def one_problem(name: str, run: Run, config: Config, space_key: str, args) -> dict:
    space = SP.parse_space(SPACES[space_key])
    names = space.names
    sel = list(range(args.select_keys))
    full = evaluator(run, config, names, sel, args.batch)
    pre = prefix_run(run, max(2, run.num_frames // 3))
    prefix = evaluator(pre, config, names, sel, args.batch)
    # Compile every shape before any clock starts.
    v0 = D.design_points(space, "sobol", args.batch, seed=123)
    c0 = time.perf_counter()
    full(v0), prefix(v0)
    compile_s = time.perf_counter() - c0

    traces = {}
    traces["sobol"] = ST.design_trace(full, space, "sobol", args.sobol, args.batch,
                                      seed=args.seed)
    traces["halton"] = ST.design_trace(full, space, "halton", args.halton, args.batch,
                                       seed=args.seed)
    traces["tpe"] = ST.tpe_search(full, space, args.tpe, args.batch, seed=args.seed)
    traces["halving"] = ST.successive_halving(prefix, full, space, args.halving,
                                              seed=args.seed)
    traces["gradient"] = gradient_trace(run, config, names, args.steps, args.runs, args.lr,
                                        args.every)

    # Re-score every incumbent on fresh keys (untimed).
    fresh_keys = list(range(1000, 1000 + args.fresh_keys))
    rescore = evaluator(run, config, names, fresh_keys, args.batch)
    rows = [v for tr in traces.values() for v in tr.incumbents]
    per_key = rescore.per_key(np.array(rows))  # [K, rows]
    fresh_all = per_key.mean(axis=0)
    fresh, i = {}, 0
    for k, tr in traces.items():
        fresh[k] = list(map(float, fresh_all[i:i + len(tr.incumbents)]))
        i += len(tr.incumbents)
    ref = fresh["sobol"][-1]
    ref_sem = float(per_key[:, len(traces["sobol"].incumbents) - 1].std(ddof=1)
                    / math.sqrt(len(fresh_keys))) if len(fresh_keys) > 1 else float("nan")
    target = 1.05 * ref
    sobol_s = traces["sobol"].seconds[-1]
    out = {"problem": name, "space": len(names), "frames": run.num_frames,
           "compile_s": round(compile_s, 1), "sobol_s": round(sobol_s, 2),
           "reference_rms_m": ref, "reference_sem_m": ref_sem, "target_rms_m": target,
           "strategies": {}}
    for k, tr in traces.items():
        t = time_to_band(tr, fresh[k], target)
        out["strategies"][k] = {
            "sets": tr.evaluated[-1], "wall_s": round(tr.seconds[-1], 2),
            "to_band_s": None if t is None else round(t, 2),
            "sets_to_band": None if t is None else tr.evaluated[tr.seconds.index(t)],
            "to_band_over_sobol": None if t is None else round(t / sobol_s, 3),
            "final_fresh_rms_m": round(fresh[k][-1], 4),
            "best_fresh_over_ref": round(min(fresh[k]) / ref, 3),
            "final": dict(zip(names, map(float, tr.incumbents[-1])))}
    print_table(out)
    return out


def print_table(o: dict) -> None:
    print(f"\n{o['problem']} ({o['frames']} frames), {o['space']} parameters: Sobol "
          f"{o['sobol_s']} s, reference RMS {o['reference_rms_m']:.4f} "
          f"+- {o['reference_sem_m']:.4f} m (fresh keys, standard error), "
          f"target {o['target_rms_m']:.4f} m", flush=True)
    print(f"  {'strategy':<9} {'sets':>5} {'wall s':>8} {'to 5% s':>8} {'n@5%':>5} "
          f"{'/ sobol':>8} {'final m':>8} {'best/ref':>8}")
    for k, s in o["strategies"].items():
        tb = "-" if s["to_band_s"] is None else f"{s['to_band_s']:.2f}"
        rt = "-" if s["to_band_over_sobol"] is None else f"{s['to_band_over_sobol']:.3f}"
        sb = "-" if s["sets_to_band"] is None else str(s["sets_to_band"])
        print(f"  {k:<9} {s['sets']:>5} {s['wall_s']:>8.2f} {tb:>8} {sb:>5} {rt:>8} "
              f"{s['final_fresh_rms_m']:>8.4f} {s['best_fresh_over_ref']:>8.3f}", flush=True)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--courses", nargs="*", default=["mars-yard-a", "mars-yard-b"])
    ap.add_argument("--frames", type=int, default=150, help="simulated course prefix (frames)")
    ap.add_argument("--kitti", type=Path, help="a KITTI Run file (gslam run --save-run)")
    ap.add_argument("--particles", type=int, default=64)
    ap.add_argument("--spaces", nargs="+", default=["4", "8"], choices=sorted(SPACES))
    ap.add_argument("--batch", type=int, default=16, help="sets per evaluator call")
    ap.add_argument("--select-keys", type=int, default=2)
    ap.add_argument("--fresh-keys", type=int, default=8)
    ap.add_argument("--sobol", type=int, default=256, help="reference Sobol points")
    ap.add_argument("--halton", type=int, default=128)
    ap.add_argument("--tpe", type=int, default=128)
    ap.add_argument("--halving", type=int, default=96)
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--runs", type=int, default=2, help="filter runs per gradient step")
    ap.add_argument("--lr", type=float, default=0.1)
    ap.add_argument("--every", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)

    import optuna
    import scipy

    problems = []
    lm = LocalMapParams(resolution=0.16, max_range=2.5, travel=1.0, cells=32)
    sim_config = Config(filter=FilterSection(particles=args.particles, unknown_cells="ignore"),
                        map=MapSection(margin=2.0))
    for course in args.courses:
        run, _ = simulate_run(course, 0, lm, max_frames=args.frames)
        problems.append((f"{course}[:{args.frames}]", run, sim_config))
    if args.kitti:
        problems.append((f"kitti {args.kitti.name}", load_run(args.kitti),
                         Config(filter=FilterSection(particles=args.particles),
                                map=MapSection(margin=2.0))))
    results = []
    t0 = time.perf_counter()
    for name, run, config in problems:
        for sp in args.spaces:
            results.append(one_problem(name, run, config, sp, args))
    env = environment()
    env.update(scipy=scipy.__version__, optuna=optuna.__version__)
    figures = {"args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
               "results": results, "total_s": round(time.perf_counter() - t0, 1),
               "environment": env}
    return report(figures, args.out)


if __name__ == "__main__":
    main()
