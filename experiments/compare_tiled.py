"""Dense JAX filter vs tiled copy-on-write reference (paper 6.3, Fig. 4): agreement, time, memory.

    python -m experiments.compare_tiled --particles 200 --out results/compare_tiled
    python -m experiments.compare_tiled --exact ...   # no FMA in XLA: bit-equal discrete choices

Default course: the simulated mars-yard-a (first 600 frames); ``--run file.npz`` uses a Run file.
"""

from __future__ import annotations

import argparse
import os
import sys


def main(argv: list[str] | None = None) -> int:
    from gslam_jax import choices  # light (no JAX): --exact still sets XLA_FLAGS first

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", help="native .npz Run (default: simulated course)")
    ap.add_argument("--particles", type=int, default=200)
    ap.add_argument("--unknown-cells", choices=choices.UNKNOWN_CELLS, default=None)
    ap.add_argument("--tile-size", type=float, default=None, help="metres (default: nearest 10 m)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="directory for compare.json and the figure")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing --out folder")
    ap.add_argument("--exact", action="store_true",
                    help="compile the dense filter without fused multiply-adds (XLA_FLAGS); "
                         "its timings are then labelled 'AVX only'")
    ap.add_argument("--store", choices=choices.MAP_STORES, default=None,
                    help="the JAX filter's map store (default: [map] store, dense)")
    args = ap.parse_args(argv)
    if args.exact:  # must be set before JAX starts its backend
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_max_isa=AVX").strip()
    from gslam_jax.run import load_run
    from gslam_jax.app.compare import compare

    run = load_run(args.run) if args.run else None
    res = compare(run, particles=args.particles, unknown_cells=args.unknown_cells,
                  tile_size=args.tile_size, seed=args.seed, out_dir=args.out, store=args.store,
                  overwrite=args.overwrite)
    return 0 if res["agreement"]["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
