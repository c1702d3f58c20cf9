"""Where a run starts in an earlier run's map, when nobody says: the map reuse of
``gslam run --prior-map`` without ``--start``.

The run's first ``travel`` metres of local maps are fused at the VO poses (the VO-only map of
paper 7.1, short enough that VO has not drifted far) and that map is aligned globally against
the prior map by the gamma likelihood (``gridmap.align_maps``): the alignment places the run's
VO frame, and with it the run's start pose, in the prior's frame. The alignment refuses a weak
or ambiguous match (``AlignmentRefused``), so a run that does not start inside the prior map is
refused rather than started in the wrong place.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from gslam_jax.gridmap import GridMap, compose
from gslam_jax.gridmap.align import AlignParams, Alignment, AlignmentRefused, align_maps
from gslam_jax.gridmap.pose_maps import pose_map
from gslam_jax.run import Run

__all__ = ["StartEstimate", "locate_start", "run_prefix"]

# the least start uncertainty given to the filter: the VO-only map's own drift over ``travel``
# metres (its heading drift moves the start by the lever arm to the map's middle) and the
# alignment's cell quantisation are not in the alignment's covariance
MIN_START_SIGMA = (0.3, 0.3, math.radians(6.0))


class StartEstimate(NamedTuple):
    """The run's start pose in the prior map's frame [3], the standard deviations to start the
    particles with [3] (metres, metres, radians), the alignment it came from and the frames of
    the run whose local maps were used."""

    start: np.ndarray
    sigma: np.ndarray
    alignment: Alignment
    frames: int


def run_prefix(run: Run, frames: int) -> Run:
    """The first ``frames`` frames of ``run`` (its local maps stay; later ones go unused)."""
    cut = slice(0, frames)
    return run._replace(
        controls=run.controls[cut], obs_index=run.obs_index[cut],
        timestamps=run.timestamps[cut],
        ground_truth=None if run.ground_truth is None else run.ground_truth[cut],
        vo_failed=None if run.vo_failed is None else run.vo_failed[cut])


# Not mutual: the reverse search (the whole prior map onto the run's first metres) has almost
# nothing to overlap and lands anywhere; the refusals by chance, ambiguity and flatness stay.
LOCATE_PARAMS = AlignParams(mutual=False)


def locate_start(prior: GridMap, run: Run, travel: float = 15.0,
                 params: AlignParams = LOCATE_PARAMS) -> StartEstimate:
    """The start of ``run`` in ``prior``'s frame from its first ``travel`` metres (all of it
    when shorter). Raises ``AlignmentRefused`` (an InputError) with a message naming the
    prefix when the prior map does not hold that stretch unambiguously."""
    vo = run.vo_poses()
    steps = np.linalg.norm(np.diff(vo[:, :2], axis=0), axis=1)
    walked = np.concatenate([[0.0], np.cumsum(steps)])
    frames = int(np.searchsorted(walked, travel, side="right"))
    frames = max(1, min(frames, run.num_frames))
    prefix = run_prefix(run, frames)
    if not np.any(prefix.obs_index >= 0):
        raise AlignmentRefused(f"the run's first {frames} frames carry no local map: nothing to "
                               "locate its start with; give --start X,Y,THETA", None)
    local = pose_map(prefix, vo[:frames])
    try:
        al = align_maps(prior, local, params)
    except AlignmentRefused as err:
        raise AlignmentRefused(f"cannot locate the run's start in the prior map from its first "
                               f"{walked[frames - 1]:.0f} m ({frames} frames): {err}; give "
                               "--start X,Y,THETA", err.alignment) from err
    start = compose(al.pose, run.start_pose())
    std = np.sqrt(np.clip(np.diag(al.covariance), 0.0, None))
    return StartEstimate(start, np.maximum(std, MIN_START_SIGMA), al, frames)
