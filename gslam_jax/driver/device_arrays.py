"""A Run as the batched search and the tuner feed it to the filter: its device arrays
(``RunArrays``: raw observations, refined on the device with the config's or the searched
settings) and the static filter config, and the frames with ground truth that their
objectives score."""

from __future__ import annotations

from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from gslam_jax import rbpf
from gslam_jax.config import Config
from gslam_jax.driver.map_axes import filtered_run
from gslam_jax.driver.observations import (ObsSettings, local_map_footprints, obs_settings,
                                           raw_observations)
from gslam_jax.driver.sizing import fallback_frames, filter_config
from gslam_jax.errors import InputError
from gslam_jax.run import Run, known_positions

__all__ = ["RunArrays", "run_arrays", "ground_truth_mask", "require_ground_truth"]


class RunArrays(NamedTuple):
    """A Run's device arrays, as the batched search and the tuner feed them to the filter."""

    controls: jax.Array    # [T, 3]
    obs_index: jax.Array   # [T]
    local_obs: jax.Array   # [M, L, L, 2] raw observations (``raw_observations``)
    lattice_headings: jax.Array  # [M] (``Run.lattice_heading_array``)
    reference: jax.Array   # [T, 3] ground truth (zeros where unknown)
    mask: jax.Array        # [T] frames with a ground-truth position (``ground_truth_mask``)
    start: jax.Array       # [3]
    obs: ObsSettings       # the config's settings for ``refine_observations``
    fallback: jax.Array | None = None  # [T] bool (``sizing.fallback_frames``; None: none)
    footprints: jax.Array | None = None  # [T, 3] (``observations.local_map_footprints``)


def ground_truth_mask(run: Run) -> np.ndarray:
    """[T] bool: frames whose ground-truth position (x, y) is finite, as
    ``metrics.errors_over_known_frames`` scores them. The RMS objective of the search and the
    supervised loss of the tuner use positions only: a NaN heading drops no frame."""
    if run.ground_truth is None:
        return np.zeros(run.num_frames, bool)
    return known_positions(run.ground_truth)


def require_ground_truth(mask: jax.Array | np.ndarray, objective: str,
                         error: type[InputError]) -> None:
    """``error`` when ``mask`` (``RunArrays.mask``) marks no frame: an objective over no frame
    with ground truth would be 0 for every parameter value."""
    if not np.any(np.asarray(mask)):
        raise error(f"objective '{objective}' needs ground truth, but the run's ground_truth "
                    f"has no frame with a finite position (x, y); use objective 'loglik'")


def run_arrays(run: Run, config: Config, varied: Sequence[str] = (),
               error: type[InputError] = InputError) -> tuple[RunArrays, rbpf.FilterConfig]:
    """Device arrays of ``run`` (raw observations, to be refined on the device with the
    config's or searched settings) and the static filter config for it; the start pose and
    the reference on the map lattice's axes (``map_heading``; the errors against the
    reference do not depend on them). ``varied``: the settings a search or the tuner varies;
    with ``fallback_scale`` among them the fallback frames' flags are kept even at a scale of
    1 (``sizing.fallback_frames``), and a run without such frames is an ``error``."""
    run = filtered_run(run, config)[2]
    keep_fallback = "fallback_scale" in varied
    fallback = fallback_frames(run, config, keep=keep_fallback)
    if keep_fallback and fallback is None:
        raise error("fallback_scale scales the motion noise of the frames whose control came "
                    "from the fallback odometry (Run.vo_failed), and this run has none: it "
                    "would change nothing; leave it out")
    T = run.num_frames
    gt = run.ground_truth if run.ground_truth is not None else np.full((T, 3), np.nan)
    arrays = RunArrays(
        controls=jnp.asarray(run.controls, jnp.float32),
        obs_index=jnp.asarray(run.obs_index, jnp.int32),
        local_obs=jnp.asarray(raw_observations(run)),
        lattice_headings=jnp.asarray(run.lattice_heading_array()),
        reference=jnp.asarray(np.nan_to_num(gt), jnp.float32),
        mask=jnp.asarray(ground_truth_mask(run)),
        start=jnp.asarray(run.start_pose(), jnp.float32),
        obs=obs_settings(config),
        fallback=None if fallback is None else jnp.asarray(fallback),
        footprints=jnp.asarray(local_map_footprints(run), jnp.float32))
    return arrays, filter_config(config, run)
