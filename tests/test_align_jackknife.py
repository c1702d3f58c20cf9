"""The alignment's uncertainty counts cells that err together: the delete-one-block jackknife
of ``gridmap.align`` against a brute force (each block removed from B and the whole alignment
run again), on a consistent map and on one bent by its own run's drift; and the mutual check's
term, against the reverse alignment run on its own and inverted by matrix inversion."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gslam_jax.gridmap import GridMap
from gslam_jax.gridmap import align as align_mod
from gslam_jax.gridmap.align import AlignParams, align_maps, map_blocks
from test_gridmap import _AlignOnce

RES = 0.16
# Every search starts at 8 x 8 cells (1.28 m; the rocks spread 0.2-0.5 m, pooled into the
# coarse cells' variance), not at the finer level the default budget allows maps this small:
# still global (every heading and shift), refined level by level to the fine lattice, and the
# brute force repeats it once per block.
COARSE = 8


pytestmark = pytest.mark.slow  # long-running: scheduled first (tests/conftest.py)


@pytest.fixture(scope="module", autouse=True)
def _search_once():
    """Each search on the lattices' axes (``_align_lattices``, which ``align_maps`` runs) is
    made once per module, remembered by its exact inputs (``_AlignOnce``): the mutual check's
    reverse search is the reverse alignment its test makes on its own, and its one-way search
    is the bent map's alignment with blocks of the jackknife test."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(align_mod, "_align_lattices", _AlignOnce(align_mod._align_lattices))
        yield


def _terrain(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Height variance at world points: smooth ground plus scattered rocks."""
    rng = np.random.default_rng(3)
    rocks = rng.uniform(-7, 7, (60, 2))
    size = rng.uniform(0.2, 0.5, 60)
    v = np.full(x.shape, 1e-3)
    for (cx, cy), s in zip(rocks, size):
        v += 0.05 * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s ** 2))
    return v


def _strip(pose: np.ndarray, half: tuple[float, float], noise: int, bend: float = 0.0,
           k: int = 30) -> GridMap:
    """A map of the terrain over a 2 half[0] x 2 half[1] strip in a frame at ``pose``; with
    ``bend`` the strip's far half (frame x > 0) is drawn ``bend`` metres off across it, as a
    run whose heading drifted halfway would lay it."""
    nx, ny = int(2 * half[0] / RES), int(2 * half[1] / RES)
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    fx = -half[0] + (i + 0.5) * RES
    fy = -half[1] + (j + 0.5) * RES + np.where(-half[0] + (i + 0.5) * RES > 0, bend, 0.0)
    c, s = math.cos(pose[2]), math.sin(pose[2])
    v = _terrain(pose[0] + c * fx - s * fy, pose[1] + s * fx + c * fy)
    S = v * np.random.default_rng(noise).chisquare(k, v.shape)
    return GridMap(np.full(v.shape, float(k)), S, (-half[0], -half[1]), RES)


def test_map_blocks_are_equal_contiguous_stretches() -> None:
    # a 40 x 10 lattice along x: 4 slabs of 10 columns, each cut in two along y
    i, j = np.meshgrid(np.arange(40), np.arange(10), indexing="ij")
    centres = np.column_stack([i.ravel() + 0.5, j.ravel() + 0.5]) * RES
    block = map_blocks(centres)
    slab = i.ravel() // 10
    side = j.ravel() >= 5
    # blocks are labelled by slab then side; the principal axis's sign is arbitrary
    for b in range(8):
        members = block == b
        assert members.sum() == 50
        assert len(set(slab[members])) == 1 and len(set(side[members])) == 1


def _brute_jackknife(a: GridMap, b: GridMap, best: np.ndarray) -> np.ndarray:
    centres = np.column_stack([b.origin[0] + (np.nonzero(b.known)[0] + 0.5) * RES,
                               b.origin[1] + (np.nonzero(b.known)[1] + 0.5) * RES])
    block = map_blocks(centres)
    rows, cols = np.nonzero(b.known)
    params = AlignParams(mutual=False, jackknife=False, coarse=COARSE)
    fits = []
    for n in range(block.max() + 1):
        k, S = b.k.copy(), b.S.copy()
        k[rows[block == n], cols[block == n]] = 0.0
        S[rows[block == n], cols[block == n]] = 0.0
        fits.append(align_maps(a, GridMap(k, S, b.origin, RES), params, refuse=False).pose)
    fits = np.asarray(fits)
    fits[:, 2] = best[2] + np.remainder(fits[:, 2] - best[2] + math.pi, 2 * math.pi) - math.pi
    d = fits - fits.mean(axis=0)
    return (len(fits) - 1) / len(fits) * d.T @ d


def test_jackknife_matches_the_brute_force_and_widens_a_bent_map() -> None:
    a = _strip(np.zeros(3), (4.5, 2.0), noise=1)
    truth = np.array([0.7, -0.4, 0.3])
    curvature_only = AlignParams(mutual=False, jackknife=False, coarse=COARSE)
    with_blocks = AlignParams(mutual=False, coarse=COARSE)

    # a consistent map: with the jackknife its error is within 2 standard deviations per axis
    straight = _strip(truth, (3.0, 1.2), noise=2)
    full = align_maps(a, straight, with_blocks, refuse=False)
    assert np.all(np.abs(full.pose - truth) < 2 * np.sqrt(np.diag(full.covariance)))

    # a map whose far half is laid 0.35 m across: the halves place differently, which the
    # curvature (as sharp as the straight map's) cannot see and the jackknife does
    bent = _strip(truth, (3.0, 1.2), noise=2, bend=0.35)
    plain = align_maps(a, bent, curvature_only, refuse=False)
    full = align_maps(a, bent, with_blocks, refuse=False)
    np.testing.assert_allclose(full.pose, plain.pose)  # the pose itself is unchanged
    jack = full.covariance - plain.covariance
    # the one-fit-per-block jackknife against whole alignments without each block
    np.testing.assert_allclose(np.sqrt(np.diag(jack)),
                               np.sqrt(np.diag(_brute_jackknife(a, bent, full.pose))),
                               rtol=0.35, atol=0.01)
    across = np.array([-math.sin(truth[2]), math.cos(truth[2]), 0.0])
    assert across @ full.covariance @ across > 9 * across @ plain.covariance @ across


def _inverse_by_matrix(pose: np.ndarray) -> np.ndarray:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    m = np.linalg.inv(np.array([[c, -s, pose[0]], [s, c, pose[1]], [0.0, 0.0, 1.0]]))
    return np.array([m[0, 2], m[1, 2], math.atan2(m[1, 0], m[0, 0])])


def test_mutual_check_adds_half_the_two_searches_disagreement() -> None:
    a = _strip(np.zeros(3), (4.5, 2.0), noise=1)
    b = _strip(np.array([0.7, -0.4, 0.3]), (3.0, 1.2), noise=2, bend=0.35)
    one_way = align_maps(a, b, AlignParams(mutual=False, coarse=COARSE), refuse=False)
    both = align_maps(a, b, AlignParams(coarse=COARSE), refuse=False)
    reverse = align_maps(b, a, AlignParams(mutual=False, coarse=COARSE), refuse=False)
    d = one_way.pose - _inverse_by_matrix(reverse.pose)
    d[2] = math.remainder(d[2], 2 * math.pi)
    assert np.all(np.abs(d) > 1e-4)  # the two searches do disagree here
    np.testing.assert_allclose(both.pose, one_way.pose)
    np.testing.assert_allclose(both.covariance - one_way.covariance, 0.5 * np.outer(d, d),
                               atol=1e-12)
