"""A run's map checked against itself (gslam_jax.gridmap.consistency): a loop driven at the true
poses is consistent; the same loop with its second visit laid 2 m off is found doubled there,
with the correction that undoes the offset."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gslam_jax.config import Config, apply_overrides
from gslam_jax.datasets.sim_path import simulate_path
from gslam_jax.gridmap.consistency import ConsistencyParams, check_consistency
from gslam_jax.gridmap.grid import arc_length
from gslam_jax.vo.localmap import localmap_params

SMALL = apply_overrides(Config(), ["localmap.max_range=5"])  # 64-cell local maps: CI-sized
PARAMS = ConsistencyParams(stretch_m=8.0, gap_m=20.0)


@pytest.fixture(scope="module")
def loop(tmp_path_factory):
    """A 40 m circle driven once and 16 m on, in the Mars Yard world."""
    from experiments.loop_paths import circle_file

    file = circle_file(tmp_path_factory.mktemp("loop"), 40.0, 16.0)
    run, _ = simulate_path(file, seed=2, course="mars-yard-a", params=localmap_params(SMALL))
    return run


def test_true_poses_are_consistent(loop) -> None:
    check = check_consistency(loop, loop.ground_truth, PARAMS)
    arc = arc_length(loop.ground_truth)
    # the second visit (after 40 m) is found as revisits, and nothing before the gap is
    assert check.revisits and all(arc[r.first_frame] >= PARAMS.gap_m for r in check.revisits)
    assert any(arc[r.first_frame] >= 40.0 for r in check.revisits)
    assert check.consistent, check.describe()
    confident = [r for r in check.revisits if r.z_best >= PARAMS.min_z]
    assert confident
    for r in confident:  # where the match is clear, the path's own placement is the best
        assert r.offset_m <= 2.5 * loop.resolution
    assert check.summary()["consistent"] is True


def test_second_visit_laid_off_is_doubled(loop) -> None:
    gt = loop.ground_truth
    arc = arc_length(gt)
    off = gt.copy()
    off[arc >= 40.0, 1] += 2.0  # the filter came back 2 m off in y
    check = check_consistency(loop, off, PARAMS)
    assert not check.consistent
    laid_off = [r for r in check.revisits if arc[r.first_frame] >= 40.0]
    assert any(r.doubled for r in laid_off)
    for r in check.doubled:
        assert arc[r.first_frame] >= 40.0  # only the laid-off visit
        # the correction moves the stretch back by about the 2 m it was laid off
        assert abs(r.offset_m - 2.0) < 0.4
        assert r.correction[1] == pytest.approx(-2.0, abs=0.4)
        assert abs(r.correction[2]) < math.radians(3.0)
        assert r.z_best - r.z_as_mapped >= PARAMS.min_gap_z
    text = check.describe()
    worst = max(check.doubled, key=lambda r: r.offset_m)
    assert "NOT consistent" in text and f"frames {worst.first_frame}-{worst.last_frame}" in text


def test_a_path_that_never_returns_has_no_revisit(loop) -> None:
    gt = loop.ground_truth
    arc = arc_length(gt)
    keep = arc < 25.0  # over half the circle, never back over the start's terrain
    run = loop._replace(obs_index=np.where(keep, loop.obs_index, -1))
    check = check_consistency(run, gt, PARAMS)
    assert check.revisits == [] and check.consistent
    with pytest.raises(ValueError, match="poses must have shape"):
        check_consistency(loop, gt[:-1], PARAMS)
