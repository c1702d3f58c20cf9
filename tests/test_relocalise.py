"""locate_start: a run's start found in an earlier map of the same terrain from its first
metres, from a frame it does not share; refused where the map is of other terrain."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gslam_jax.datasets.sim import simulate_run
from gslam_jax.gridmap.align import AlignmentRefused
from gslam_jax.gridmap.pose_maps import pose_map
from gslam_jax.gridmap.relocalise import locate_start, run_prefix
from gslam_jax.vo.localmap import LocalMapParams

PARAMS = LocalMapParams(resolution=0.16, max_range=8.0)


# A run's start is located from its first 15 m (about 110 frames here): the runs are a little
# longer than that, the prior map about twice as long (26 m of Mars Yard A), so the run's
# start is searched for over a map of which it covers a part.
PRIOR_FRAMES, RUN_FRAMES = 200, 150


@pytest.fixture(scope="module")
def prior():
    """Mars Yard A's first PRIOR_FRAMES frames mapped at the true poses (world frame)."""
    run, _ = simulate_run("mars-yard-a", seed=0, params=PARAMS, max_frames=PRIOR_FRAMES)
    return pose_map(run, run.ground_truth)


def test_start_is_found_from_an_unknown_frame(prior) -> None:
    run, _ = simulate_run("mars-yard-a", seed=0, params=PARAMS, max_frames=RUN_FRAMES,
                          noise_seed=9)
    truth = run.ground_truth[0].copy()
    moved = run._replace(initial_pose=np.array([40.0, -25.0, 2.0]))  # B's own frame
    found = locate_start(prior, moved)
    # within the spread the particles start with (the VO-only map's heading drift over its
    # first metres is the largest error: a lever arm to the start)
    error = found.start - truth
    error[2] = math.remainder(error[2], 2 * math.pi)
    assert np.all(np.abs(error) < 2 * found.sigma), (error, found.sigma)
    assert math.hypot(error[0], error[1]) < 0.5
    assert 0 < found.frames < run.num_frames


def test_other_terrain_is_refused(prior) -> None:
    run, _ = simulate_run("maze", seed=3, params=PARAMS, max_frames=RUN_FRAMES)
    with pytest.raises(AlignmentRefused, match="cannot locate the run's start"):
        locate_start(prior, run)


def test_run_prefix_cuts_every_per_frame_field() -> None:
    run, _ = simulate_run("mars-yard-a", seed=0, params=PARAMS, max_frames=50)
    cut = run_prefix(run, 20)
    assert cut.num_frames == 20 and cut.ground_truth.shape == (20, 3)
    np.testing.assert_array_equal(cut.controls, run.controls[:20])
