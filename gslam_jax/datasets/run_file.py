"""A native ``.npz`` Run file (``gslam_jax.run``): frames already through a front-end, used as
they are (``gslam run FILE.npz``; ``--save-run`` writes one)."""

from __future__ import annotations

from gslam_jax.config import Config
from gslam_jax.datasets.registry import RUN_FILE, DataSource, LoadedSource, Progress, Source
from gslam_jax.run import load_run

__all__ = ["SOURCE"]


def _load(src: Source, config: Config, progress: Progress | None = None) -> LoadedSource:
    return LoadedSource(load_run(src.run_file), str(src.run_file))


SOURCE = DataSource(name=RUN_FILE, help="a native .npz Run file", load=_load,
                    path="the .npz Run file", cuts_frames=False)
