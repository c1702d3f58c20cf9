"""The window store against the shared-tile store on KITTI 00's 1057 m loop (issue 67): filter
time and peak RSS per store and J, each run in its own process (so its peak RSS is its own),
in the same invocation, with the machine and versions printed beside them.

    python -m experiments.window_store --particles 2000 --stores shared window
    python -m experiments.window_store --particles 2000 --frames 1500   # the first 1500 frames
    python -m experiments.window_store --point window 2000 1500         # one point (JSON)
    python -m experiments.window_store --revisit 200 --stores dense window  # out and back

``--revisit J``: the update's cost on new ground and on a revisit, without the loop's data:
J particles (0.3 m, 0.05 rad apart) drive 30 local maps 1.12 m apart straight out and the
same 30 back over what they mapped, with the benchmark's synthetic 128 x 128 local map
(``bench.synthetic_local_map``, its first 4096 observed cells), ``[map] tile = 16``; each
store compiled on a copy first, then the two legs timed from empty maps.

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


def revisit(J: int, store: str, legs: int = 30) -> dict:
    """us per particle per update of ``store`` out over new ground and back over it
    (``--revisit``)."""
    import time

    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax import lax

    from gslam_jax import rbpf
    from gslam_jax.app.bench import synthetic_local_map
    from gslam_jax.rbpf import maps

    L, H, W, res = 128, 1024, 320, 0.16
    cfg = maps.resolve_history(rbpf.FilterConfig(
        num_particles=J, map_shape=(H, W), map_origin=(0.0, 0.0), resolution=res, local_size=L,
        observed_cells=4096, store=store, tile=WINDOW_TILE, unknown_cells="ignore"), 2 * legs)
    rng = np.random.default_rng(0)
    obs, params = synthetic_local_map(rng, L), rbpf.FilterParams()
    noise = rbpf.update_noise(jax.random.key(0), cfg)
    start = np.array([20.0, 0.5 * W * res, 0.0], np.float32)
    spread = rng.normal(0.0, [0.3, 0.3, 0.05], (J, 3)).astype(np.float32)
    state = rbpf.init(cfg, jnp.asarray(start))._replace(pose=jnp.asarray(start + spread))

    def drive(s, steps):
        def one(s, d):
            s = s._replace(pose=s.pose + d)
            return rbpf.update(s, obs, noise.unknown_u, params, cfg)[0], None
        return lax.scan(one, s, steps)[0]

    drive = jax.jit(drive, donate_argnums=0)
    out = jnp.broadcast_to(jnp.asarray([1.12, 0.0, 0.0], jnp.float32), (legs, J, 3))
    jax.block_until_ready(drive(jax.tree_util.tree_map(jnp.copy, state), out))
    times = []
    for steps in (out, -out):
        t = time.perf_counter()
        state = jax.block_until_ready(drive(state, steps))
        times.append(1e6 * (time.perf_counter() - t) / legs / J)
    return {"store": store, "particles": J, "new_ground_us": times[0], "revisit_us": times[1],
            "map_status": int(maps.status(state.maps))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--particles", type=int, nargs="+", default=[2000])
    ap.add_argument("--stores", nargs="+", default=["shared", "window"])
    ap.add_argument("--frames", type=int, default=0, help="first N frames only (0: all)")
    ap.add_argument("--cache", type=Path, default=Path("results/window_store"))
    ap.add_argument("--json", type=Path)
    ap.add_argument("--point", nargs=3, metavar=("STORE", "J", "FRAMES"))
    ap.add_argument("--revisit", type=int, metavar="J",
                    help="time --stores out and back over synthetic local maps at J particles")
    args = ap.parse_args(argv)
    if args.revisit:
        for store in args.stores:
            print(json.dumps(revisit(args.revisit, store)), flush=True)
        return 0
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
