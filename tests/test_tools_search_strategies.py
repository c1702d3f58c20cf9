"""experiments/search_strategies.py: the course prefix and the time to the 5% band."""


import numpy as np
from synthetic import make_run

from experiments import search_strategies as B
from gslam_jax.run import validate_run
from gslam_jax.tuning import strategies as ST


def test_prefix_run_keeps_the_frames_and_the_local_maps_they_use():
    run, _ = make_run(steps=30)
    pre = validate_run(B.prefix_run(run, 10))
    assert pre.num_frames == 10
    used = run.obs_index[:10]
    assert pre.num_local_maps == max(1, used.max() + 1)
    np.testing.assert_array_equal(pre.local_maps, run.local_maps[:pre.num_local_maps])
    np.testing.assert_array_equal(pre.ground_truth, run.ground_truth[:10])


def test_time_to_band_is_the_first_incumbent_within_the_target():
    tr = ST.Trace([1.0, 2.0, 3.0], [np.zeros(1)] * 3, [0.3, 0.2, 0.1], [8, 16, 24])
    assert B.time_to_band(tr, [0.30, 0.104, 0.09], 0.105) == 2.0
    assert B.time_to_band(tr, [0.30, 0.2, 0.11], 0.105) is None
