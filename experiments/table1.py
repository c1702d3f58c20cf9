"""Regenerate the paper's Table I on the five simulated courses.

    python experiments/table1.py                 # J = 200, seeds 0 1 2, all courses
    python experiments/table1.py --quick         # Mars Yard A, one seed, J = 100 (~2 minutes)
"""

import argparse
import sys
from pathlib import Path

from gslam_jax.app.table1 import PAPER_TABLE1, main

if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--courses", nargs="+", default=list(PAPER_TABLE1))
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--particles", type=int, default=None,
                   help="J (default: the config's filter.particles, 200 without a config)")
    p.add_argument("--config", type=Path)
    p.add_argument("--json", type=Path)
    p.add_argument("--quick", action="store_true")
    a = p.parse_args()
    sys.exit(main(a.courses, a.seeds, a.particles, a.config, a.json, a.quick))
