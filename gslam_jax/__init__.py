"""gslam-jax: Gamma-SLAM (Marks et al., Journal of Field Robotics 26(1), 2009) in JAX.

Where things live, lowest layer first (``tests/test_layers.py`` keeps imports going down):

* ``config``, ``choices``, ``errors``, ``machine``, ``io``: settings and shared basics;
* ``rbpf``: the paper's filter math: ``cells`` (eq. 14 update, eq. 26 log predictive),
  ``motion`` (eqs. 1-3), ``resampling``, ``tempering``, ``unknown`` (eq. 31), the map store
  (``maps``, ``tilestore``) and the kernel (``init``, ``step``, ``scan_frames``);
* ``run``: the ``Run`` container (controls, local maps) and its ``.npz`` format;
* ``vo``: the stereo front-end, images -> VO increments -> points -> ``localmap``;
* ``sim``: the simulator; ``tiled``: the independent copy-on-write reference;
  ``gridmap``: finished maps as values (``GridMap``), their global alignment by the gamma
  likelihood (``align_maps``) and merging (``merge_maps``, ``merge_runs``);
* ``metrics``: RMS after the rigid fit, drift, maps at given poses;
* ``datasets``: the sources of frames, one module each (``datasets.registry``);
  ``relocalise``: where a run starts in an earlier map (``locate_start``);
  ``consistency``: a run's map checked against itself (``check_consistency``: terrain mapped
  twice);
* ``slam``: the host driver, ``run_slam(run, config)``;
* ``online``: the same filter one frame at a time for a live robot (``Online``);
* ``gps``: alignment to GPS, UTM, georeferenced outputs; ``tuning``: parameter search, optax
  tuning, motion-noise fit;
* ``app``: the ``gslam`` command line, ``gslam run`` as functions, results, figures.

The names below are imported on first use, so ``import gslam_jax`` stays light (no JAX).
"""

from __future__ import annotations

import importlib
from typing import Any

from gslam_jax.version import __version__

_EXPORTS = {
    "Config": "gslam_jax.config",
    "load_config": "gslam_jax.config",
    "parse_config": "gslam_jax.config",
    "Run": "gslam_jax.run",
    "load_run": "gslam_jax.run",
    "save_run": "gslam_jax.run",
    "run_slam": "gslam_jax.slam",
    "SlamResult": "gslam_jax.slam",
    "PriorMap": "gslam_jax.map_reuse",
    "MapExtent": "gslam_jax.sizing",
    "Online": "gslam_jax.online",
    "OnlineFrame": "gslam_jax.online",
    "OnlineStats": "gslam_jax.online",
    "MapEdgeError": "gslam_jax.online",
    "simulate_run": "gslam_jax.datasets.sim",
    "GridMap": "gslam_jax.gridmap",
    "load_map": "gslam_jax.gridmap",
    "align_maps": "gslam_jax.gridmap.align",
    "merge_maps": "gslam_jax.gridmap.merge",
    "merge_runs": "gslam_jax.gridmap.merge",
    "load_run_folder": "gslam_jax.gridmap.merge",
    "locate_start": "gslam_jax.gridmap.relocalise",
    "check_consistency": "gslam_jax.gridmap.consistency",
    "Source": "gslam_jax.datasets.registry",
    "load_source": "gslam_jax.app.pipeline",
    "run_pipeline": "gslam_jax.app.pipeline",
}

__all__ = ["__version__", *_EXPORTS]


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'gslam_jax' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
