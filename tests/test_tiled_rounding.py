"""The tiled reference follows another filter's resampling only where the two differ by
rounding (float32 weights against float64): checked against a float32 inverse CDF written here,
and refused for choices that differ for real."""

from __future__ import annotations

import numpy as np
import pytest

from gslam_jax.tiled import numerics as nm


def _float32_ancestors(scheme: str, w: np.ndarray, u: np.ndarray) -> np.ndarray:
    """What a float32 filter picks: the inverse CDF of float32 weights summed in float32."""
    w32 = np.asarray(w, np.float32)
    cdf = np.cumsum(w32, dtype=np.float32)
    cdf = cdf / cdf[-1]
    J = w.size
    pos = {"multinomial": u, "systematic": (np.arange(J) + u[0]) / J,
           "stratified": (np.arange(J) + u) / J}[scheme].astype(np.float32)
    raw = np.clip(np.searchsorted(cdf, pos, side="right"), 0, J - 1)
    return nm.survivors_keep_slots(raw)


def _weights(rng: np.random.Generator, J: int) -> np.ndarray:
    log_w = rng.normal(0, 2.0, J)
    return np.exp(log_w - np.logaddexp.reduce(log_w))


@pytest.mark.parametrize("scheme", ["multinomial", "systematic", "stratified"])
def test_float32_choices_within_rounding_are_followed(scheme):
    """Weights off by up to LOG_W_ROUNDING in the log, then float32 sums: every differing
    ancestor set is explained by draws within rounding of a boundary; draws are placed at
    boundaries (within 1e-6) so that the float32 filter picks differently often."""
    rng = np.random.default_rng(0)
    J, differed = 200, 0
    for _ in range(60):
        w = _weights(rng, J)
        u = rng.uniform(0, 1, J)
        cdf = np.cumsum(w) / np.sum(w)
        if scheme == "multinomial":  # some draws right at a boundary
            at = rng.choice(J - 1, 20, replace=False)
            u[:20] = cdf[at] + rng.uniform(-1e-6, 1e-6, 20)
        other = w * np.exp(rng.uniform(-nm.LOG_W_ROUNDING, nm.LOG_W_ROUNDING, J))
        theirs = _float32_ancestors(scheme, other / other.sum(), u)
        ours = nm.survivors_keep_slots(nm.resample(scheme, w, u))
        taken = nm.follow_ancestors(scheme, w, u, theirs)
        assert taken is not None
        np.testing.assert_array_equal(taken[0], theirs)
        if not np.array_equal(ours, theirs):
            differed += 1
            assert taken[1] >= 1 and taken[2] <= nm.cdf_rounding(J)
        else:
            assert taken[1] == 0
    assert differed >= 5  # the rounding case is exercised


@pytest.mark.parametrize("scheme", ["multinomial", "systematic", "stratified"])
def test_real_differences_are_not_followed(scheme):
    """Other uniforms, or one ancestor moved to a particle far along the CDF, are refused."""
    rng = np.random.default_rng(1)
    J = 100
    w = _weights(rng, J)
    u = rng.uniform(0, 1, J)
    ours = nm.survivors_keep_slots(nm.resample(scheme, w, u))
    other_u = nm.survivors_keep_slots(nm.resample(scheme, w, rng.uniform(0, 1, J)))
    assert nm.follow_ancestors(scheme, w, u, other_u) is None
    raw = nm.resample(scheme, w, u)
    raw[0] = (raw[0] + J // 2) % J
    assert nm.follow_ancestors(scheme, w, u, nm.survivors_keep_slots(raw)) is None
    assert nm.follow_ancestors("residual", w, u, ours) is None  # not an inverse CDF


def test_decisions_within_rounding_of_the_threshold():
    threshold = nm.resample_threshold(0.5, 200)
    assert threshold == pytest.approx(100.1)
    assert nm.decision_within_rounding(threshold * (1 + 0.9 * nm.ESS_ROUNDING), threshold)
    assert nm.decision_within_rounding(threshold * (1 - 0.9 * nm.ESS_ROUNDING), threshold)
    assert not nm.decision_within_rounding(threshold * (1 + 2 * nm.ESS_ROUNDING), threshold)
    # the bound: weights off by d in the log move the ESS by a factor within e^(+-4d)
    rng = np.random.default_rng(2)
    for _ in range(200):
        w = _weights(rng, 200)
        other = w * np.exp(rng.choice([-1.0, 1.0], 200) * nm.LOG_W_ROUNDING)
        other /= other.sum()
        ess, ess_other = 1 / np.sum(w ** 2), 1 / np.sum(other ** 2)
        assert abs(ess_other / ess - 1) <= nm.ESS_ROUNDING * (1 + 1e-3)
