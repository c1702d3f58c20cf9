"""Synthetic Runs built once per test process and shared by the CLI tests, and the one filter
setting they run it with.

``make_run`` (``synthetic.py``) renders every frame's points and builds the local maps, a few
seconds of CPU per call; the CLI tests only need a Run file, so they share these. The Run's
arrays are read-only here: a test that changes one copies it (``Run._replace`` with new arrays).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
from synthetic import make_run

from gslam_jax.run import Run, save_run

FRAMES = 25  # the CLI tests' run length (0.2 s a frame: 0-4.8 s on the run's clock)
# One filter setting for every `gslam run` on the shared Run, in every file: the filter's
# programs are compiled once and the persistent compilation cache (conftest.py) serves them to
# the other files and workers. resample_ratio 0.3 (not the default 0.5) is what
# test_cli_inputs.test_ess_plot_threshold_is_the_resample_ratio looks for.
RUN_SETTINGS = ("--set", "filter.particles=8", "--set", "map.margin=1.0",
                "--set", "filter.resample_ratio=0.3")


@lru_cache(maxsize=None)
def shared_run(steps: int = FRAMES, seed: int = 0) -> Run:
    """``make_run(seed, steps)``'s Run, built once; its arrays are made read-only so that a
    test cannot change what the next test sees."""
    run, _ = make_run(seed=seed, steps=steps)
    for value in run:
        if isinstance(value, np.ndarray):
            value.flags.writeable = False
    return run


def run_file(path: Path, steps: int = FRAMES, **changes) -> tuple[Run, Path]:
    """The shared Run, with ``changes`` (``Run._replace``), saved to ``path``."""
    run = shared_run(steps)._replace(**changes)
    save_run(path, run)
    return run, path
