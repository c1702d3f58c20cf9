"""The Gamma-SLAM Rao-Blackwellized particle filter on dense per-particle maps (paper 6.1-6.2).

Modules, one idea each:

* ``types``: ``FilterConfig`` (static), ``FilterParams`` (tunable), ``FilterState`` (the
  particles), ``UpdateNoise``, ``Observation``, ``UpdateInfo``, ``StepInfo``, ``RunOutput``;
* ``footprint``: where a local map lands in each particle's map and what an update reads there;
* ``importance``: the log importance factor of each particle (eqs. 26, 30 / 31);
* ``maps``: the map store seam (allocate, read cells, scatter-add, copy on resampling), in
  front of the dense store and the shared-tile store (``tilestore``);
* ``kernel``: ``init``, ``predict``, ``update`` (weigh, write, normalise), ``resample``
  (ESS-gated), ``step`` (one frame), ``scan_frames`` and ``run_filter``.
"""

from gslam_jax.rbpf.footprint import (compact_observation, observation_cells, window_origin,
                                      written_rows)
from gslam_jax.rbpf.importance import log_importance
from gslam_jax.rbpf.kernel import (Proposal, Resampler, ancestors, backtrack_path, best_slot,
                                   frame_keys, init, motion_noise, observe, predict, propagate,
                                   resample, run_filter, scan_frames, smoothed_mean_path, step,
                                   update,
                                   update_noise)
from gslam_jax.rbpf.maps import ROW_BAND, gather_particles, map_status, particle_map
from gslam_jax.rbpf.types import (CPU_BLOCK_CELLS, STORES, UNKNOWN_MODES, FilterConfig,
                                  FilterParams, FilterState, Observation, RunOutput, StepInfo,
                                  UpdateInfo, UpdateNoise)

__all__ = [
    # types
    "FilterConfig", "FilterParams", "FilterState", "UpdateNoise", "Observation", "UpdateInfo",
    "StepInfo", "RunOutput", "UNKNOWN_MODES", "CPU_BLOCK_CELLS", "STORES",
    # kernel
    "Proposal", "Resampler", "init", "motion_noise", "update_noise", "predict", "propagate",
    "update", "ancestors", "resample", "observe", "step", "scan_frames", "frame_keys",
    "run_filter", "backtrack_path", "smoothed_mean_path", "best_slot",
    # footprint, importance, map store
    "compact_observation", "observation_cells", "window_origin", "written_rows",
    "log_importance", "gather_particles", "ROW_BAND", "particle_map", "map_status",
]
