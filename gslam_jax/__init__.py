"""gslam-jax: Gamma-SLAM (Marks et al., Journal of Field Robotics 26(1), 2009) in JAX.

Where things live, lowest layer first (``tests/test_layers.py`` keeps imports going down):

* ``config``, ``choices``, ``errors``, ``io``, ``version``: settings and shared basics;
* ``rbpf``: the paper's filter math: ``cells`` (eq. 14 update, eq. 26 log predictive),
  ``motion`` (eqs. 1-3), ``resampling``, ``tempering``, ``unknown`` (eq. 31), the map store
  behind its seam (``maps``) and the kernel (``init``, ``step``, ``scan_frames``);
* ``run``: the ``Run`` container (controls, local maps), its checks and its ``.npz`` format;
* ``vo``: the stereo front-end, images -> VO increments -> points -> ``localmap``;
* ``tiled``: the independent copy-on-write reference;
* ``gridmap``: finished maps as values (``GridMap``), built from a run at given poses
  (``pose_maps``), their global alignment by the gamma likelihood (``align_maps``), merging
  (``merge_maps``, ``merge_runs``), where a run starts in an earlier map (``relocalise``:
  ``locate_start``) and a run's map checked against itself (``consistency``:
  ``check_consistency``, terrain mapped twice);
* ``sim``: the simulator; ``evaluation``: RMS after the rigid fit, drift (``metrics``) and loop
  closure (``loops``);
* ``datasets``: the sources of frames, one module each (``datasets.registry``);
* ``driver``: the host side of a run: ``run_slam(run, config)`` (``driver.slam``) and its
  results, the settings for a Run (``sizing``), its observations, the map's axes, prior maps
  (``map_reuse``), the device arrays of the search and the tuner, the machine's memory, and
  the same filter one frame at a time for a live robot (``online.Online``);
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
    "run_slam": "gslam_jax.driver.slam",
    "SlamResult": "gslam_jax.driver.results",
    "PriorMap": "gslam_jax.driver.map_reuse",
    "MapExtent": "gslam_jax.driver.sizing",
    "Online": "gslam_jax.driver.online",
    "OnlineFrame": "gslam_jax.driver.online",
    "OnlineStats": "gslam_jax.driver.online",
    "MapEdgeError": "gslam_jax.driver.online",
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
