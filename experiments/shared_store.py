"""Map memory and time per update of the dense and the shared-tile store against J and course
length (issue 17): every point is one ``run_slam`` over a simulated course, in its own process
(so its peak RSS is its own).

    python -m experiments.shared_store --out results/shared_store            # the sweep + plot
    (points are kept in OUT/points and reused; simulated courses in results/shared_store/runs)
    python -m experiments.shared_store --point mars-yard-a 10000 shared 0   # one point (JSON)
    python -m experiments.shared_store --ab 3      # dense vs shared per update as run, A/B x 3

Time per update: the filter's wall time after its first chunk of ``CHUNK`` frames (which
compiles), divided by the local-map updates after it, resampling included (as run). Memory:
the store's allocation (dense maps or the tile pool), the most its maps held at once (shared:
live tiles and page tables) and the process's peak RSS (JAX runtime, run and outputs included).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

CHUNK = 64  # frames in run_slam's first (compiling) chunk, not timed


def point(course: str, J: int, store: str, frames: int, unknown_cells: str = "ignore",
          pool_tiles: int = 0) -> dict:
    """One run; ``frames`` 0: the whole course."""
    import dataclasses
    import resource

    import numpy as np

    from gslam_jax.config import Config
    from gslam_jax.driver import sizing, slam
    from gslam_jax.rbpf import maps

    c = Config()
    config = dataclasses.replace(
        c, filter=dataclasses.replace(c.filter, particles=J, unknown_cells=unknown_cells),
        map=dataclasses.replace(c.map, store=store, pool_tiles=pool_tiles))
    run = _course_run(course, frames, config)
    res = slam.run_slam(run, config, chunk=CHUNK)
    timed = int(np.sum(np.asarray(run.obs_index)[CHUNK:] >= 0))
    cfg = sizing.filter_config(config, run)
    MB = 2 ** 20
    return {"course": course, "particles": J, "store": res.store, "unknown_cells": unknown_cells,
            "frames": run.num_frames, "updates": run.num_local_maps, "timed_updates": timed,
            "map": list(cfg.map_shape),
            "pool_tiles": maps.pool_tiles(cfg) if res.store == "shared" else 0,
            "ms_per_update": 1e3 * res.seconds / max(timed, 1),
            "resamplings": int(res.resampled.sum()),
            "map_alloc_MB": res.map_bytes / MB, "map_peak_MB": res.map_peak_bytes / MB,
            "peak_rss_MB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def ab(rounds: int, particles: int = 200, unknown_cells: str = "ignore") -> dict:
    """Time per local-map update as run (``compare.time_dense_updates``: every update of
    ``gslam compare``'s run, resampling included) of the dense and the shared store,
    alternating in one process, ``rounds`` times each."""
    import dataclasses

    import jax
    import numpy as np

    from gslam_jax.app.compare import default_run, time_dense_updates
    from gslam_jax.config import Config
    from gslam_jax.driver import observations, sizing

    run = default_run()
    c = Config()
    config = dataclasses.replace(
        c, filter=dataclasses.replace(c.filter, particles=particles, unknown_cells=unknown_cells),
        map=dataclasses.replace(c.map, resolution=run.resolution))
    cfg, params = sizing.filter_config(config, run), sizing.filter_params(config)
    obs = observations.local_observations(run, config.map.min_variance)
    out: dict = {"dense": [], "shared": []}
    for _ in range(rounds):
        for store in out:
            t, _ = time_dense_updates(jax.random.key(0), params, run, obs,
                                      cfg._replace(store=store))
            out[store].append(1e3 * float(np.mean(t)))
            print(f"{store:>7}: {out[store][-1]:.2f} ms per update as run", flush=True)
    ratio = [s / d for s, d in zip(out["shared"], out["dense"])]
    print(f"shared / dense per round: {', '.join(f'{r:.2f}' for r in ratio)}")
    return {**out, "ratio": ratio, "particles": particles, "unknown_cells": unknown_cells}


RUN_CACHE = Path("results/shared_store/runs")  # simulated courses, made once per (course, frames)


def _course_run(course: str, frames: int, config):
    """The simulated course (seed 0, the config's local maps), cached as a Run file."""
    from gslam_jax.datasets.sim import simulate_run
    from gslam_jax.run import load_run, save_run
    from gslam_jax.vo.localmap import localmap_params

    path = RUN_CACHE / f"{course}_{frames}.npz"
    if path.exists():
        return load_run(path)
    run, _ = simulate_run(course, seed=0, params=localmap_params(config),
                          max_frames=frames or None)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_run(path, run)
    return run


def _spawn(out_dir: Path, *args, cached_only: bool = False) -> dict:
    """One point in its own process; its JSON is kept in ``out_dir/points`` and reused."""
    cached = out_dir / "points" / ("_".join(map(str, args)) + ".json")
    if cached.exists():
        return json.loads(cached.read_text())
    if cached_only:
        return {"args": list(map(str, args)), "error": ["not measured (--cached-only)"]}
    root = str(Path(__file__).resolve().parents[1])  # this checkout's gslam_jax, not another
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        p for p in (root, os.environ.get("PYTHONPATH")) if p)}
    out = subprocess.run([sys.executable, __file__, "--point", *map(str, args)],
                         capture_output=True, text=True, env=env)
    if out.returncode:
        return {"args": list(map(str, args)), "error": out.stderr.strip().splitlines()[-1:]}
    cached.parent.mkdir(parents=True, exist_ok=True)
    cached.write_text(out.stdout.strip().splitlines()[-1])
    return json.loads(cached.read_text())


def plot(rows: list[dict], path: Path) -> None:
    from gslam_jax.app.plots import plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 4))
    ok = [r for r in rows if "error" not in r]
    for (course, store) in sorted({(r["course"], r["store"]) for r in ok}):
        full = sorted((r["particles"], r) for r in ok if r["course"] == course and r["store"] == store
                      and r["frames_setting"] == 0)
        if full:
            J = [j for j, _ in full]
            axes[0].plot(J, [r["map_peak_MB"] for _, r in full], "o-", label=f"{course}, {store}")
            axes[1].plot(J, [r["ms_per_update"] / j * 1e3 for j, r in full], "o-",
                         label=f"{course}, {store}")
        by_len = sorted((r["frames"], r) for r in ok if r["course"] == course and r["store"] == store
                        and r["particles"] == 200)
        if len(by_len) > 1:
            axes[2].plot([f for f, _ in by_len], [r["map_peak_MB"] for _, r in by_len], "o-",
                         label=f"{course}, {store}, J = 200")
    axes[0].set(xscale="log", yscale="log", xlabel="particles J", ylabel="peak map memory (MB)")
    axes[1].set(xscale="log", xlabel="particles J", ylabel="us per particle per update (as run)")
    axes[2].set(xlabel="course length (frames)", ylabel="peak map memory (MB)")
    for a in axes:
        a.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--point", nargs="+", metavar="ARG",
                    help="course J store frames [unknown_cells [pool_tiles]]: one point as JSON")
    ap.add_argument("--courses", nargs="+", default=["mars-yard-a", "maze"])
    ap.add_argument("--particles", type=int, nargs="+", default=[200, 1000, 10000])
    ap.add_argument("--lengths", type=int, nargs="+", default=[300, 600],
                    help="truncated lengths (frames) of the first course at J = 200, beside "
                    "the whole course")
    ap.add_argument("--out", type=Path, default=Path("results/shared_store"))
    ap.add_argument("--ab", type=int, metavar="ROUNDS",
                    help="only the A/B of time per update as run, dense vs shared (J = 200)")
    ap.add_argument("--unknown-cells", choices=("ignore", "sample"), default="ignore")
    ap.add_argument("--cached-only", action="store_true",
                    help="table and plot from the points already measured; run none")
    args = ap.parse_args(argv)
    if args.ab:
        from gslam_jax.app.bench import environment

        for k, v in environment().items():
            print(f"  {k}: {v}")
        ab(args.ab, unknown_cells=args.unknown_cells)
        return 0
    if args.point:
        p = args.point
        kw = {"unknown_cells": p[4]} if len(p) > 4 else {}
        if len(p) > 5:
            kw["pool_tiles"] = int(p[5])
        print(json.dumps(point(p[0], int(p[1]), p[2], int(p[3]), **kw)))
        return 0
    from gslam_jax.app.bench import environment

    env = environment()
    for k, v in env.items():
        print(f"  {k}: {v}")
    args.out.mkdir(parents=True, exist_ok=True)
    plan = [(c, 200, "dense", 0) for c in args.courses]
    plan += [(c, J, "shared", 0) for c in args.courses for J in args.particles]
    plan += [(args.courses[0], 200, s, n) for s in ("dense", "shared") for n in args.lengths]
    rows = []
    print(f"{'course':>12} {'J':>6} {'store':>7} {'frames':>7} {'ms/update':>10} {'map alloc MB':>13} "
          f"{'map peak MB':>12} {'peak RSS MB':>12}")
    for c, J, store, n in plan:
        r = _spawn(args.out, c, J, store, n, cached_only=args.cached_only)
        r["frames_setting"] = n
        rows.append(r)
        if "error" in r:
            print(f"{c:>12} {J:>6} {store:>7} {n:>7}   failed: {r['error']}", flush=True)
            continue
        print(f"{c:>12} {J:>6} {store:>7} {r['frames']:>7} {r['ms_per_update']:>10.1f} "
              f"{r['map_alloc_MB']:>13.1f} {r['map_peak_MB']:>12.1f} {r['peak_rss_MB']:>12.0f}",
              flush=True)
    (args.out / "shared_store.json").write_text(json.dumps({"environment": env, "rows": rows},
                                                           indent=1))
    plot(rows, args.out / "shared_store.png")
    print(f"wrote {args.out / 'shared_store.json'} and {args.out / 'shared_store.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
