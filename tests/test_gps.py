"""GPS alignment (eqs. A.1-A.10): batch vs online, reflection fix, exact recovery, bad input."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from gslam_jax import gps


_align = jax.jit(gps.align)  # one compiled call per shape instead of eager op-by-op dispatch


def _rot(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def _cost_at(theta, b: np.ndarray, a: np.ndarray, w: np.ndarray):
    """Eq. A.1 minimised over l for fixed rotation angles [K] (weighted least squares in l)."""
    c, s = np.cos(theta)[..., None], np.sin(theta)[..., None]
    rb = np.stack([c * b[:, 0] - s * b[:, 1], s * b[:, 0] + c * b[:, 1]], -1)  # [K, T, 2]
    l = np.sum(w[:, None] * (a - rb), -2, keepdims=True) / w.sum()
    return np.sum(w * np.sum((a - rb - l) ** 2, -1), -1)


def _brute_force(b: np.ndarray, a: np.ndarray, epe: np.ndarray) -> tuple[float, float]:
    w = 1.0 / epe**2
    grid = np.linspace(-np.pi, np.pi, 20001)
    t0 = grid[np.argmin(_cost_at(grid, b, a, w))]
    res = minimize_scalar(lambda t: float(_cost_at(np.asarray(t), b, a, w)),
                          bounds=(t0 - 1e-3, t0 + 1e-3), method="bounded",
                          options={"xatol": 1e-12})
    return float(res.x), float(res.fun)


def test_online_equals_batch_after_every_reading_float64():
    rng = np.random.default_rng(0)
    J, T = 3, 60
    with jax.enable_x64(True):
        a = rng.normal(0, 50, (T, 2))
        paths = rng.normal(0, 40, (J, T, 2))
        epe = rng.uniform(2, 12, T)
        valid = rng.random(T) > 0.15
        a[7, 1] = np.nan          # bad readings that must be skipped and counted
        epe[11] = 0.0
        epe[13] = -3.0
        paths[1, 17, 0] = np.inf  # bad only for particle 1
        valid[[7, 11, 13, 17]] = True
        a, paths, epe, valid = map(jnp.asarray, (a, paths, epe, valid))
        assert a.dtype == jnp.float64

        upd = jax.vmap(gps.online_update, in_axes=(0, 0, None, None, None))

        def step(state, xs):
            b_t, a_t, e_t, v_t = xs
            state = upd(state, b_t, a_t, e_t, v_t)
            return state, jax.vmap(gps.online_solve)(state)

        init = gps.online_init((J,), jnp.float64)
        _, online = jax.lax.scan(step, init, (jnp.swapaxes(paths, 0, 1), a, epe, valid))

        prefix = valid[None, :] & (jnp.arange(T)[:, None] >= jnp.arange(T)[None, :])
        batch = jax.jit(jax.vmap(lambda m: gps.align_particles(paths, a, epe, m)[0]))(prefix)

        np.testing.assert_array_equal(online.n_used, batch.n_used)
        np.testing.assert_array_equal(online.n_skipped, batch.n_skipped)
        np.testing.assert_array_equal(online.ok, batch.ok)
        assert int(batch.n_skipped[-1, 0]) == 3 and int(batch.n_skipped[-1, 1]) == 4
        ok = np.asarray(batch.ok)
        assert ok.sum() > 0.8 * ok.size
        for name in ("R", "l", "cost"):
            x, y = np.asarray(getattr(online, name)), np.asarray(getattr(batch, name))
            scale = 1.0 if name == "R" else max(1.0, np.abs(y[ok]).max())
            np.testing.assert_allclose(x[ok], y[ok], rtol=0, atol=1e-9 * scale, err_msg=name)
        R = np.asarray(online.R)[ok]
        np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)


def test_reflection_case_gives_proper_rotation_matching_brute_force():
    rng = np.random.default_rng(1)
    T = 25
    b = rng.normal(0, 20, (T, 2))
    mirror = np.diag([1.0, -1.0])
    a = b @ (_rot(0.4) @ mirror).T + np.array([30.0, -5.0]) + rng.normal(0, 1.0, (T, 2))
    epe = rng.uniform(3, 10, T)

    # Independent check that this really is the reflection case of eq. A.8.
    w = 1 / epe**2
    ac = a - np.sum(w[:, None] * a, 0) / w.sum()
    bc = b - np.sum(w[:, None] * b, 0) / w.sum()
    U, _, Vt = np.linalg.svd((w[:, None] * ac).T @ bc)
    assert np.linalg.det(U @ Vt) < 0

    al = _align(b.astype(np.float32), a.astype(np.float32), epe.astype(np.float32))
    R = np.asarray(al.R, np.float64)
    assert abs(np.linalg.det(R) - 1.0) < 1e-5
    theta_bf, cost_bf = _brute_force(b, a, epe)
    theta = np.arctan2(R[1, 0], R[0, 0])
    assert abs(np.angle(np.exp(1j * (theta - theta_bf)))) < 2e-5
    np.testing.assert_allclose(float(al.cost), cost_bf, rtol=1e-4)
    # The plain (unfixed) solution U V^T would be a reflection: our R must beat no proper
    # rotation, and l must be the optimal translation for it.
    l_bf = np.sum(w[:, None] * (a - b @ _rot(theta_bf).T), 0) / w.sum()
    np.testing.assert_allclose(np.asarray(al.l), l_bf, atol=2e-3)


def test_generic_case_matches_brute_force_float64():
    rng = np.random.default_rng(2)
    T = 40
    b = np.cumsum(rng.normal(0, 2, (T, 2)), 0)
    a = b @ _rot(-2.1).T + np.array([400.0, 250.0]) + rng.normal(0, 5, (T, 2))
    epe = rng.uniform(3, 10, T)
    with jax.enable_x64(True):
        al = _align(b, a, epe)
        theta = float(jnp.arctan2(al.R[1, 0], al.R[0, 0]))
        cost = float(al.cost)
    theta_bf, cost_bf = _brute_force(b, a, epe)
    assert abs(theta - theta_bf) < 1e-7
    np.testing.assert_allclose(cost, cost_bf, rtol=1e-9)


@pytest.mark.parametrize("x64", [False, True])
def test_noise_free_rigid_transform_recovered_exactly_per_particle(x64):
    rng = np.random.default_rng(3)
    J, T = 5, 30
    thetas = rng.uniform(-np.pi, np.pi, J)
    ls = rng.uniform(-200, 200, (J, 2))
    a = rng.uniform(-100, 100, (T, 2))
    epe = rng.uniform(3, 10, T)
    # Each particle's path is the GPS track seen through its own rigid transform.
    paths = np.stack([(a - ls[j]) @ _rot(thetas[j]) for j in range(J)])
    with jax.enable_x64(x64):
        dt = jnp.float64 if x64 else jnp.float32
        al, aligned = jax.jit(gps.align_particles)(jnp.asarray(paths, dt), jnp.asarray(a, dt),
                                                   jnp.asarray(epe, dt))
        assert al.R.dtype == dt and aligned.dtype == dt
        tol = 1e-10 if x64 else 2e-5
        for j in range(J):
            np.testing.assert_allclose(np.asarray(al.R[j]), _rot(thetas[j]), atol=tol)
            np.testing.assert_allclose(np.asarray(al.l[j]), ls[j], atol=tol * 400)
        np.testing.assert_allclose(np.asarray(aligned), np.broadcast_to(a, (J, T, 2)),
                                   atol=tol * 400)
        assert np.all(np.asarray(al.ok)) and np.all(np.asarray(al.n_used) == T)
        # The cost's rounding floor is ~eps * sum w|a|^2.
        np.testing.assert_allclose(np.asarray(al.cost), 0.0, atol=1e-9 if x64 else 1e-2)


def test_float32_online_close_to_float64_batch():
    rng = np.random.default_rng(4)
    T = 500
    b = np.cumsum(rng.normal(0, 1, (T, 2)), 0)
    a = b @ _rot(0.3).T + np.array([800.0, -600.0]) + rng.normal(0, 5, (T, 2))
    epe = rng.uniform(3, 10, T)
    step = jax.jit(gps.online_update)
    state = gps.online_init()
    for t in range(5):
        state = step(state, b[t], a[t], epe[t])
    assert step._cache_size() == 1  # one trace for every reading
    state, _ = jax.lax.scan(lambda st, x: (gps.online_update(st, *x), None), state,
                            (jnp.asarray(b[5:], jnp.float32), jnp.asarray(a[5:], jnp.float32),
                             jnp.asarray(epe[5:], jnp.float32)))
    al32 = jax.jit(gps.online_solve)(state)
    assert al32.R.dtype == jnp.float32
    with jax.enable_x64(True):
        al64 = _align(b, a, epe)
        # float32 rounding of R is ~1.5e-5 here; the bound leaves a margin.
        np.testing.assert_allclose(np.asarray(al32.R), np.asarray(al64.R), atol=5e-5)
        np.testing.assert_allclose(np.asarray(al32.l), np.asarray(al64.l), atol=5e-3)


def test_bad_input_flags_and_counts():
    # Fewer than two usable readings: not ok.
    b = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 1.0]], np.float32)
    a = b + 10.0
    al = _align(b, a, np.array([5.0, np.nan, 0.0], np.float32))
    assert not bool(al.ok) and int(al.n_used) == 1 and int(al.n_skipped) == 2
    al = gps.online_solve(gps.online_init())
    assert not bool(al.ok) and np.all(np.isfinite(np.asarray(al.R)))
    # A robot that never moves leaves the rotation undetermined.
    al = _align(np.zeros((5, 2), np.float32), np.random.default_rng(0).normal(size=(5, 2)),
                   np.full(5, 4.0, np.float32))
    assert not bool(al.ok) and int(al.n_used) == 5
    # Skipped readings change nothing else: same result as dropping them by hand.
    rng = np.random.default_rng(5)
    b = rng.normal(0, 10, (12, 2)).astype(np.float32)
    a = (b @ _rot(1.0).T + 3 + rng.normal(0, 1, (12, 2))).astype(np.float32)
    epe = rng.uniform(3, 10, 12).astype(np.float32)
    a_bad, epe_bad = a.copy(), epe.copy()
    a_bad[2] = np.nan
    epe_bad[5] = -1.0
    keep = np.ones(12, bool)
    keep[[2, 5]] = False
    al_bad, al_ref = _align(b, a_bad, epe_bad), _align(b[keep], a[keep], epe[keep])
    assert int(al_bad.n_skipped) == 2 and int(al_bad.n_used) == 10
    for x, y in zip(al_bad[:3], al_ref[:3]):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-5, atol=1e-5)


def test_transform_poses_and_align_to_gps_errors():
    al = gps.Alignment(jnp.asarray(_rot(np.pi / 2), jnp.float32), jnp.array([1.0, 2.0]),
                       jnp.float32(0), jnp.int32(3), jnp.int32(0), jnp.bool_(True))
    out = np.asarray(jax.jit(gps.transform_poses)(al, jnp.array([[1.0, 0.0, 3.0]])))
    np.testing.assert_allclose(out, [[1.0, 3.0, 3.0 + np.pi / 2 - 2 * np.pi]], atol=1e-5)
    times = np.arange(10.0)
    path = np.stack([times, np.zeros(10)], -1)
    with pytest.raises(ValueError, match="at least 2 usable"):
        gps.align_to_gps(times, path, np.r_[5.0, np.arange(20.0, 29.0)], np.zeros((10, 2)),
                         np.ones(10))
    with pytest.raises(ValueError, match="does not move"):
        gps.align_to_gps(times, np.zeros((10, 2)), times, np.zeros((10, 2)), np.ones(10))


def test_readings_in_span_marks_what_align_to_gps_uses():
    times = np.arange(10) * 0.5  # SLAM clock 0 .. 4.5 s
    gps_time = np.array([-1.0, 0.0, 2.2, 4.5, 4.6, 30.0])
    assert gps.readings_in_span(times, gps_time).tolist() == [False, True, True, True, False, False]
    path = np.column_stack([times, np.sin(times)])
    al, _ = gps.align_to_gps(times, path, gps_time, np.column_stack(
        [np.interp(gps_time, times, path[:, 0]), np.interp(gps_time, times, path[:, 1])]),
        np.ones(6))
    assert int(al.n_used) == 3
