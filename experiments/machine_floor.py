"""This machine's memory bandwidth and arithmetic throughput, the floor a map store's update
is measured against (docs/particle-budget.md, issue 67).

    python -m experiments.machine_floor [--mb 256] [--repeats 5]

Prints the machine and versions and the load average, then for NumPy and for jitted JAX on
the CPU: stream copy and in-place scale (bytes read + written per second), triad a + s b (the
same), a random gather and
a random scatter-add of float32 over a buffer far larger than the cache (the access pattern of
a footprint read / eq. 14 write into a big map), the same gather into a 128 KiB buffer (a
window cache that stays in L2), and float32 fused multiply-adds per second (a dependent-free
polynomial kept in registers). Best of ``--repeats``.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from gslam_jax.driver.machine import environment


def _best(fn, repeats: int) -> float:
    fn()
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - t)
    return best


def measure(mb: int = 256, repeats: int = 5) -> dict:
    n = mb * 2 ** 20 // 4
    rng = np.random.default_rng(0)
    a = rng.random(n, dtype=np.float32)
    b = rng.random(n, dtype=np.float32)
    out = np.empty_like(a)
    m = 1 << 22  # random accesses
    idx_big = rng.integers(0, n, m).astype(np.int32)
    small = 32768  # 128 KiB of float32
    idx_small = rng.integers(0, small, m).astype(np.int32)
    vals = rng.random(m, dtype=np.float32)
    r = {}
    # NumPy
    t = _best(lambda: np.copyto(out, a), repeats)
    r["numpy_copy_GBps"] = 2 * a.nbytes / t / 1e9
    t = _best(lambda: np.add(a, np.multiply(b, np.float32(1.5), out=out), out=out), repeats)
    r["numpy_triad_GBps"] = 3 * a.nbytes / t / 1e9  # a, b read, out written (twice touched)
    t = _best(lambda: np.take(a, idx_big, out=vals), repeats)
    r["numpy_gather_big_Mps"] = m / t / 1e6
    # JAX (jit, CPU)
    ja, jb = jnp.asarray(a), jnp.asarray(b)
    # in place (donated): a fresh output buffer would time the page faults of its allocation
    scale = jax.jit(lambda x: x * 1.0000001, donate_argnums=0)
    cur = [ja]

    def sc_():
        cur[0] = scale(cur[0])
        return cur[0]

    t = _best(sc_, repeats)
    r["jax_scale_in_place_GBps"] = 2 * a.nbytes / t / 1e9
    triad = jax.jit(lambda x, y: x + 1.5 * y, donate_argnums=0)

    def tr_():
        cur[0] = triad(cur[0], jb)
        return cur[0]

    t = _best(tr_, repeats)
    r["jax_triad_in_place_GBps"] = 3 * a.nbytes / t / 1e9
    ja = cur[0]
    ji, jv = jnp.asarray(idx_big), jnp.asarray(vals)
    gather = jax.jit(lambda x, i: x.at[i].get(mode="promise_in_bounds"))
    t = _best(lambda: gather(ja, ji), repeats)
    r["jax_gather_big_Mps"] = m / t / 1e6
    scatter = jax.jit(lambda x, i, v: x.at[i].add(v, mode="promise_in_bounds"),
                      donate_argnums=0)
    buf = [jnp.zeros(n, jnp.float32)]

    def sc():
        buf[0] = scatter(buf[0], ji, jv)
        return buf[0]

    t = _best(sc, repeats)
    r["jax_scatter_add_big_Mps"] = m / t / 1e6
    js = jnp.asarray(idx_small)
    jsmall = jnp.asarray(a[:small])
    t = _best(lambda: gather(jsmall, js), repeats)
    r["jax_gather_128KiB_Mps"] = m / t / 1e6
    sbuf = [jnp.zeros(small, jnp.float32)]

    def sc_small():
        sbuf[0] = scatter(sbuf[0], js, jv)
        return sbuf[0]

    t = _best(sc_small, repeats)
    r["jax_scatter_add_128KiB_Mps"] = m / t / 1e6
    x = jnp.asarray(rng.random(1 << 20, dtype=np.float32))

    @jax.jit
    def fma(x):  # 64 dependent-free FMA per element, kept in registers
        y = x
        for i in range(64):
            y = y * 0.999 + 0.001
        return y

    t = _best(lambda: fma(x), repeats)
    r["jax_fma_GFlops"] = 2 * 64 * x.size / t / 1e9
    lg = jax.jit(lambda x: jnp.log(x + 1.0))
    t = _best(lambda: lg(x), repeats)  # 4 MiB: in cache, the arithmetic alone
    r["jax_log_Gps"] = x.size / t / 1e9
    return r


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mb", type=int, default=256, help="buffer size, MiB (>> cache)")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    env = environment()
    print(f"# {env['date']} | {env['cpus']} cpus | jax {env['jax']} | numpy {np.__version__}"
          f" | {jax.devices()[0].device_kind} | load average {os.getloadavg()[0]:.1f}",
          flush=True)
    r = measure(args.mb, args.repeats)
    for k, v in r.items():
        print(f"{k:>28} {v:10.2f}")
    print(json.dumps(r))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
