"""The window store against the shared-tile store on KITTI 00's 1057 m loop (issue 67): filter
time and peak RSS per store and J, each run in its own process (so its peak RSS is its own),
in the same invocation, with the machine and versions printed beside them.

    python -m experiments.window_store --particles 2000 --stores shared window
    python -m experiments.window_store --particles 2000 --frames 1500   # the first 1500 frames
    python -m experiments.window_store --point window 2000 1500         # one point (JSON)

The loop: poses 200-1633 of ../shared/data/kitti-poses/00.txt driven through the Arroyo A
corridor world (``--source sim-path``), its 20 m overlap and the Arroyo settings of
``experiments.loop_closure`` (configs/table1.toml, course arroyo-a, map margin 0.1 m per metre
of loop), seed 0, the window store with ``[map] tile = 16`` (the loop's local maps are 7
cells apart), except eq. 30 (``unknown_cells = "ignore"``: the window store does not do
eq. 31) for every store. The simulated Run is made once and kept in --cache. ``--frames N``
runs the first N frames only (``relocalise.run_prefix``: its map sized from that stretch).
Time: ``SlamResult.seconds`` (the filter after its first ``CHUNK`` frames, which compile;
resampling included) and per local-map update after them; memory: the store's allocation and the process's peak RSS. The runs use
the same random numbers, so where both stores run they agree: the final best particle's pose
and the number of resamplings are printed for each.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

KITTI = Path("../shared/data/kitti-poses/00.txt")
SETTINGS = ["filter.unknown_cells=ignore"]
CHUNK = 64  # frames of run_slam's first chunk, which compiles: not in the filter time
WINDOW_TILE = 16  # [map] tile of the window store: cells it may move between local maps


def _config(store: str, J: int):
    from gslam_jax.config import layered_config
    from gslam_jax.sim.courses import COURSES

    extra = [f"map.tile={WINDOW_TILE}"] if store == "window" else []
    return layered_config(Path("configs/table1.toml"), "arroyo-a",
                          SETTINGS + extra + [f"map.store={store}", f"filter.particles={J}",
                                              "filter.seed=0"], courses=COURSES)


def cached_run(cache: Path):
    """The KITTI 00 loop's Run (seed 0) and its map margin, simulated once into ``cache``."""
    from gslam_jax.run import load_run, save_run

    file = cache / "kitti00-200-1633-seed0.npz"
    meta = cache / "kitti00-200-1633-seed0.json"
    if file.exists():
        return load_run(file), json.loads(meta.read_text())["margin"]
    from experiments.loop_closure import simulate_loop
    from experiments.loop_paths import kitti_loops

    with tempfile.TemporaryDirectory() as tmp:
        loop = [x for x in kitti_loops(Path(tmp), KITTI, [1000], 2.0, 20.0)][0]
        if loop.name != "kitti00-200-1633":
            raise SystemExit(f"expected the 200-1633 loop, got {loop.name}")
        run, config = simulate_loop(loop.file, loop.length_m, 0, _config("dense", 1),
                                    "arroyo-a")
    cache.mkdir(parents=True, exist_ok=True)
    save_run(file, run)
    meta.write_text(json.dumps({"margin": config.map.margin, "loop": loop.name,
                                "length_m": loop.length_m}))
    return run, config.map.margin


def point(store: str, J: int, frames: int, cache: Path) -> dict:
    """One run of the loop (its first ``frames`` frames; 0: all) with ``store`` at J."""
    import resource
    import time

    import numpy as np

    from gslam_jax.driver import slam
    from gslam_jax.config import apply_overrides
    from gslam_jax.gridmap.relocalise import run_prefix

    run, margin = cached_run(cache)
    if frames:
        run = run_prefix(run, frames)
    config = apply_overrides(_config(store, J), [f"map.margin={margin:g}"])
    t0 = time.perf_counter()
    res = slam.run_slam(run, config, chunk=CHUNK)
    wall = time.perf_counter() - t0
    updates = int(np.sum(np.asarray(run.obs_index)[CHUNK:] >= 0))  # after the first chunk
    return {"store": res.store, "particles": J, "frames": run.num_frames, "updates": updates,
            "filter_s": res.seconds, "compile_s": res.compile_seconds, "wall_s": wall,
            "us_per_particle_update": 1e6 * res.seconds / max(updates, 1) / J,
            "map_alloc_MB": res.map_bytes / 2 ** 20,
            "peak_rss_MB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "resamplings": int(np.sum(res.resampled)),
            "best_path_end": np.asarray(res.best_pose)[-1].tolist()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--particles", type=int, nargs="+", default=[2000])
    ap.add_argument("--stores", nargs="+", default=["shared", "window"])
    ap.add_argument("--frames", type=int, default=0, help="first N frames only (0: all)")
    ap.add_argument("--cache", type=Path, default=Path("results/window_store"))
    ap.add_argument("--json", type=Path)
    ap.add_argument("--point", nargs=3, metavar=("STORE", "J", "FRAMES"))
    args = ap.parse_args(argv)
    if args.point:
        store, J, frames = args.point
        print(json.dumps(point(store, int(J), int(frames), args.cache)))
        return 0
    from gslam_jax.driver.machine import environment

    env = environment()
    print(f"# {env['date']} | {env.get('cpu', '')} | {env['cpus']} cpus | jax {env['jax']}",
          flush=True)
    cached_run(args.cache)
    rows = []
    for J in args.particles:
        for store in args.stores:
            out = subprocess.run([sys.executable, "-m", "experiments.window_store", "--point",
                                  store, str(J), str(args.frames), "--cache", str(args.cache)],
                                 capture_output=True, text=True)
            if out.returncode:
                print(f"{store:>7} J={J}: failed: {out.stderr.strip().splitlines()[-1:]}",
                      flush=True)
                rows.append({"store": store, "particles": J, "error": out.stderr[-2000:]})
                continue
            r = json.loads(out.stdout.strip().splitlines()[-1])
            rows.append(r)
            print(f"{r['store']:>7} J={J:<6} {r['frames']} frames {r['updates']} updates: "
                  f"filter {r['filter_s']:7.1f} s ({r['us_per_particle_update']:6.1f} us per "
                  f"particle per update; compile {r['compile_s']:.1f} s) | maps "
                  f"{r['map_alloc_MB']:8.0f} MB | peak RSS {r['peak_rss_MB']:8.0f} MB | "
                  f"{r['resamplings']} resamplings | best end {r['best_path_end']}", flush=True)
    if args.json:
        args.json.write_text(json.dumps({"environment": env, "frames": args.frames,
                                         "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
