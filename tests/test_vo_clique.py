"""Rigidity-clique inlier detection (Hirschmuller 2002 / Howard 2008) on synthetic matches."""

from __future__ import annotations

import itertools

import numpy as np
from scipy.spatial.transform import Rotation

from gslam_jax.vo.clique import consistency_graph, greedy_max_clique, rigid_inliers
from gslam_jax.vo.estimate import Camera, estimate_motion, project

CAM = Camera(500.0, 500.0, 256.0, 192.0, 0.12)


def _scene(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.column_stack([rng.uniform(-4, 4, n), rng.uniform(-1, 1.5, n), rng.uniform(2, 12, n)])


def test_graph_matches_loop_reference():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(40, 3)), rng.normal(size=(40, 3))
    tol = rng.uniform(0.1, 0.5, 40)
    w = consistency_graph(a, b, tol)
    for i, j in itertools.product(range(40), repeat=2):
        ref = i != j and abs(np.linalg.norm(a[i] - a[j]) - np.linalg.norm(b[i] - b[j])) < tol[i] + tol[j]
        assert w[i, j] == ref


def test_greedy_clique_is_a_clique_and_finds_planted_one():
    rng = np.random.default_rng(1)
    n = 120
    w = rng.random((n, n)) < 0.2
    w = np.triu(w, 1)
    w = w | w.T
    planted = rng.choice(n, 30, replace=False)
    w[np.ix_(planted, planted)] = True
    np.fill_diagonal(w, False)
    c = greedy_max_clique(w)
    sub = w[np.ix_(c, c)] | np.eye(len(c), dtype=bool)
    assert sub.all()
    assert set(planted) <= set(c)


def test_clique_recovers_motion_with_60_percent_false_matches():
    rng = np.random.default_rng(2)
    n_true, n_false = 80, 120
    rot = Rotation.from_euler("xyz", [1.0, 6.0, -2.0], degrees=True)
    t = np.array([0.10, -0.03, 0.45])
    wb = _scene(rng, n_true)
    wa = rot.apply(wb) + t  # X_a = R X_b + t
    ja, jb = project(CAM, wa), project(CAM, wb)
    # False matches: real points of frame a paired with unrelated points of frame b.
    ja = np.vstack([ja, project(CAM, _scene(rng, n_false))])
    jb = np.vstack([jb, project(CAM, _scene(rng, n_false))])
    noise = rng.normal(scale=0.2, size=ja.shape)
    ja, jb = ja + noise, jb + rng.normal(scale=0.2, size=jb.shape)
    perm = rng.permutation(len(ja))
    ja, jb = ja[perm], jb[perm]
    is_true = perm < n_true
    from gslam_jax.vo.estimate import triangulate
    wa_m, wb_m = triangulate(CAM, ja), triangulate(CAM, jb)
    z = np.maximum(wa_m[:, 2], wb_m[:, 2])
    inl = rigid_inliers(wa_m, wb_m, 0.025 + z * z / (CAM.fx * CAM.baseline) * 0.5)
    assert is_true[inl].mean() > 0.95, "clique admitted false matches"
    assert is_true[inl].sum() > 0.7 * n_true, "clique lost most true matches"
    est = estimate_motion(CAM, ja[inl], jb[inl])
    ang = np.degrees((Rotation.from_matrix(est.transform[:3, :3]) * rot.inv()).magnitude())
    assert ang < 0.3
    assert np.linalg.norm(est.transform[:3, 3] - t) < 0.03


def test_clique_keeps_true_matches_at_500_matches():
    """The 500-match case of the speed benchmark (experiments/bench_vo.py prints its time:
    speed lives in the benchmark, not in a timed test that a busy CI machine could fail)."""
    rng = np.random.default_rng(3)
    a = _scene(rng, 500)
    b = a + rng.normal(scale=0.003, size=a.shape)
    b[250:] = _scene(rng, 250)
    inl = rigid_inliers(a, b, 0.05)
    assert np.isin(np.arange(250), inl).mean() > 0.95 and (inl < 250).all()
