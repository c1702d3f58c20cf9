"""Where one local-map update spends its time: XLA's own per-thunk trace of ``rbpf.update``.

Runs the same chained updates as ``gslam bench`` under ``jax.profiler`` and sums the trace
events of every fused computation per update (XLA CPU runs independent thunks, e.g. the k and S
scatter-adds, on different threads, so the rows can add up to more than the wall time).

    python -m experiments.profile_update --particles 200 --local 64 --map 640
"""

from __future__ import annotations

import argparse
import collections
import glob
import tempfile

import jax
import jax.numpy as jnp
import numpy as np


from gslam_jax import choices, rbpf  # noqa: E402
from gslam_jax.app.bench import (bench_config, chained, synthetic_local_map,  # noqa: E402
                                  synthetic_state)
from gslam_jax.driver.machine import environment  # noqa: E402


def main(argv: list[str] | None = None) -> dict[str, float]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--particles", type=int, default=200)
    ap.add_argument("--local", type=int, default=64)
    ap.add_argument("--map", type=int, default=640)
    ap.add_argument("--mode", default="ignore", choices=choices.UNKNOWN_CELLS)
    ap.add_argument("--calls", type=int, default=3, help="traced calls of --chain updates")
    ap.add_argument("--chain", type=int, default=10)
    ap.add_argument("--top", type=int, default=15)
    args = ap.parse_args(argv)

    J, L, side = args.particles, args.local, args.map
    rng = np.random.default_rng(0)
    cfg = bench_config(J, L, side, args.mode)
    obs = synthetic_local_map(rng, L)
    params = rbpf.FilterParams()
    noise = rbpf.update_noise(jax.random.key(0), cfg)

    def one(s: rbpf.FilterState) -> rbpf.FilterState:
        s = rbpf.update(s, obs, noise.unknown_u, params, cfg)[0]
        # Move the particles a little so that XLA cannot hoist the reads out of the loop.
        return s._replace(pose=s.pose + 1e-4 * jnp.tanh(s.log_w)[:, None])

    fn = chained(one, args.chain)
    state = jax.block_until_ready(fn(synthetic_state(cfg, rng)))  # compile
    with tempfile.TemporaryDirectory() as tmp:
        jax.profiler.start_trace(tmp)
        for _ in range(args.calls):
            state = jax.block_until_ready(fn(state))
        jax.profiler.stop_trace()
        trace = sorted(glob.glob(f"{tmp}/**/*.xplane.pb", recursive=True))[-1]
        data = jax.profiler.ProfileData.from_file(trace)
        per = collections.Counter()
        wall = collections.Counter()
        for plane in data.planes:
            for line in plane.lines:
                for ev in line.events:
                    if line.name.startswith("tf_XLAEigen"):
                        if ev.name == "ThunkExecutor::Execute":
                            wall[line.name] += ev.duration_ns
                        else:
                            per[ev.name] += ev.duration_ns
    updates = args.calls * args.chain
    print(f"profile of rbpf.update: J = {J}, local {L}, map {side}, {args.mode}; "
          f"{updates} updates")
    print(f"  {environment()}")
    busy = {name: ns / updates / 1e6 for name, ns in wall.items()}
    print("  busy ms per update per XLA thread: "
          + ", ".join(f"{v:.2f}" for v in sorted(busy.values(), reverse=True)))
    rows = {name: ns / updates / 1e6 for name, ns in per.most_common(args.top)}
    for name, ms in rows.items():
        print(f"  {ms:8.3f} ms  {1e3 * ms / J:7.2f} us/particle  {name}")
    return rows


if __name__ == "__main__":
    main()
