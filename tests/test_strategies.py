"""Search strategies over a batched evaluator, checked on a known function (no filter)."""

import numpy as np
import pytest

from gslam_jax.tuning import designs as D
from gslam_jax.tuning import space as SP
from gslam_jax.tuning import strategies as ST

SPACE = SP.parse_space({"alpha_d": {"range": [0.001, 1.0], "log": True}, "beta_new": [0.01, 1.0],
                       "obs_weight": [0.1, 1.0]})
OPT = np.array([0.03, 0.4, 0.7])


def bowl(values):
    v = np.asarray(values)
    return (np.log(v[:, 0] / OPT[0])) ** 2 + (v[:, 1] - OPT[1]) ** 2 + (v[:, 2] - OPT[2]) ** 2


def counting(f):
    calls = []

    def g(values):
        calls.append(len(values))
        return f(values)

    return g, calls


def _check_trace(tr):
    assert len(tr.seconds) == len(tr.incumbents) == len(tr.scores) == len(tr.evaluated)
    assert np.all(np.diff(tr.scores) <= 0) and np.all(np.diff(tr.seconds) >= 0)
    np.testing.assert_allclose(bowl(np.array(tr.incumbents)), tr.scores)


def test_design_trace_keeps_the_best_so_far():
    f, calls = counting(bowl)
    tr = ST.design_trace(f, SPACE, "sobol", 64, 16, seed=2)
    assert calls == [16] * 4 and tr.evaluated == [16, 32, 48, 64]
    _check_trace(tr)
    values = D.design_points(SPACE, "sobol", 64, seed=2)
    for i, n in enumerate(tr.evaluated):  # brute force: the best of the first n points
        np.testing.assert_array_equal(tr.incumbents[i], values[np.argmin(bowl(values[:n]))])


def test_successive_halving_keeps_the_best_third_of_the_prefix_scores():
    noise = np.random.default_rng(0).normal(0, 0.05, 30)
    prefix = lambda v: bowl(v) + noise[:len(v)]  # noqa: E731
    full, calls = counting(bowl)
    tr = ST.successive_halving(prefix, full, SPACE, 30, keep=1 / 3, seed=1)
    values = D.design_points(SPACE, "sobol", 30, seed=1)
    kept = values[np.argsort(prefix(values))[:10]]
    assert calls == [10] and tr.evaluated == [40]
    np.testing.assert_array_equal(tr.incumbents[0], kept[np.argmin(bowl(kept))])


def test_tpe_asks_batches_and_beats_its_random_start():
    pytest.importorskip("optuna", reason="Optuna is the optional [tpe] extra (also in [dev])")
    f, calls = counting(bowl)
    tr = ST.tpe_search(f, SPACE, 96, 16, seed=0)
    assert calls == [16] * 6
    _check_trace(tr)
    for v in tr.incumbents:
        assert all(lo <= x <= hi for x, lo, hi in zip(v, SPACE.lo, SPACE.hi))
    # The model's batches improve on the best of the random first batch.
    assert tr.scores[-1] < 0.5 * tr.scores[0]
    again = ST.tpe_search(bowl, SPACE, 96, 16, seed=0)
    np.testing.assert_array_equal(np.array(again.incumbents), np.array(tr.incumbents))
