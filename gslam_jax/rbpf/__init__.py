"""The Gamma-SLAM Rao-Blackwellized particle filter (paper 6.1-6.2).

Modules, one idea each:

* ``cells``: the per-cell conjugate model (eq. 14) and its log predictive (eq. 26);
* ``motion``: the motion model (eqs. 1-3); ``resampling``: the resamplers (eq. 23);
  ``tempering``: the adaptive exponent on the importance factors; ``unknown``: eq. 31's
  sampler of known cells;
* ``types``: ``FilterConfig`` (static), ``FilterParams`` (tunable), ``FilterState`` (the
  particles), ``UpdateNoise``, ``UpdateInfo``, ``StepInfo``, ``RunOutput``;
* ``footprint``: where a local map lands in each particle's map and what an update reads there;
* ``importance``: the log importance factor of each particle (eqs. 26, 30 / 31);
* ``maps``: the map-store seam (allocate, read, write, copy on resampling, sizing) in front
  of the dense store (``densestore``) and the shared-tile store (``tilestore``, with its
  host-side byte counts and errors in ``tilebytes``);
* ``draws``: the random numbers of each frame (keys, the proposal's normals, an update's
  uniforms), so that the tiled reference can be driven with the same ones;
* ``kernel``: ``init``, ``predict``, ``update`` (weigh, write, normalise), ``resample``
  (ESS-gated), ``step`` (one frame), ``scan_frames`` and ``run_filter``;
* ``paths``: trajectory estimates (the best particle's path, the mode's, the smoother's mean
  path and mean steps) and which particle's map goes with each.

This package exports what a user of the filter calls; the rest is imported from its module.
"""

from gslam_jax.rbpf.draws import frame_keys, motion_noise, standard_normals, update_noise
from gslam_jax.rbpf.kernel import (Proposal, Resampler, init, mean_noise_scale, observe, predict,
                                   resample, run_filter, scan_frames, step, update)
from gslam_jax.rbpf.maps import particle_map
from gslam_jax.rbpf.paths import (StepHistory, ancestry_path, backtrack_path, densest_particle,
                                  factor_cover, local_step_path, map_particle, mode_mean_path,
                                  smoothed_mean_path, smoothed_step_path, step_history)
from gslam_jax.rbpf.types import (FilterConfig, FilterParams, FilterState, RunOutput, StepInfo,
                                  UpdateInfo, UpdateNoise)

__all__ = [
    # types
    "FilterConfig", "FilterParams", "FilterState", "UpdateNoise", "UpdateInfo", "StepInfo",
    "RunOutput", "Proposal", "Resampler",
    # the filter
    "init", "standard_normals", "motion_noise", "update_noise", "predict", "update", "resample",
    "observe", "step", "scan_frames", "frame_keys", "run_filter",
    # results
    "backtrack_path", "densest_particle", "smoothed_mean_path", "mode_mean_path",
    "smoothed_step_path", "StepHistory", "step_history", "factor_cover", "local_step_path",
    "ancestry_path", "map_particle", "particle_map", "mean_noise_scale",
]
