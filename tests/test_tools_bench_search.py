"""experiments/bench_search.py checks the batched search against the loop set by set."""


import numpy as np
import pytest

from experiments import bench_search as B
from gslam_jax.tuning import search as S


def test_objectives_are_compared_per_parameter_set():
    values = np.array([[0.1, 1.0], [0.2, 2.0], [0.3, 3.0], [0.4, 4.0]])
    loop = [3.0, 1.0, 4.0, 2.0]  # the loop's objectives, in design order
    vals, obj = S.rank(values, np.asarray(loop), maximize=False)  # as search returns them
    res = S.SearchResult(("alpha_d", "beta_prev"), vals, obj, "rms", False, 0.0, 0.0)
    np.testing.assert_array_equal(B.objective_in_design_order(values, res), loop)
    assert B.max_difference(values, loop, res) == 0.0
    # Two sets' objectives exchanged: the sorted lists still agree, the sets do not.
    swapped = res._replace(objective=obj[[1, 0, 2, 3]])
    assert np.max(np.abs(np.sort(loop) - np.sort(swapped.objective))) == 0.0
    assert B.max_difference(values, loop, swapped) == 1.0
    with pytest.raises(ValueError, match="not in the result"):
        B.max_difference(values + 1.0, loop, res)
