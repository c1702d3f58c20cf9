"""``experiments.loop_bound``: the motion model's draws against the closed form on a straight
drive, the chance of one particle within the tolerance and the J that reaches a share, and the
experiment end to end at CI size."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gslam_jax.rbpf.motion import MotionParams


def test_draws_along_a_straight_drive_have_the_closed_form_spread() -> None:
    """Only along-track noise (eq. 2, alpha_d) on a straight drive along x: the end's x is
    Gaussian with mean the sum of the steps and variance alpha_d^2 sum(s_t^2 d_t^2), s_t the
    fallback scale on the flagged frames and 1 elsewhere; y and the heading do not move."""
    from experiments.loop_bound import motion_draws

    rng = np.random.default_rng(0)
    T = 300
    steps = rng.uniform(0.05, 0.3, T)
    controls = np.stack([steps, np.zeros(T), np.zeros(T)], 1)
    fallback = rng.random(T) < 0.2
    params = MotionParams(0.05, 0.0, 0.0, 0.0, 3.0)
    N = 40000
    pose = np.asarray(motion_draws(jax.random.key(1), jnp.array([1.0, -2.0, 0.0]), controls,
                                   fallback, params, N), np.float64)
    var = 0.05 ** 2 * np.sum(np.where(fallback, 3.0, 1.0) ** 2 * steps ** 2)
    assert np.mean(pose[:, 0]) == pytest.approx(1.0 + steps.sum(), abs=4 * np.sqrt(var / N))
    # the sample variance of N Gaussians: relative standard error sqrt(2 / N)
    assert np.var(pose[:, 0]) == pytest.approx(var, rel=4 * np.sqrt(2.0 / N))
    np.testing.assert_allclose(pose[:, 1:], np.broadcast_to([-2.0, 0.0], (N, 2)), atol=1e-5)
    # without the flags the variance is the VO's alone
    pose = np.asarray(motion_draws(jax.random.key(1), jnp.zeros(3), controls, np.zeros(T, bool),
                                   params, N), np.float64)
    assert np.var(pose[:, 0]) == pytest.approx(0.05 ** 2 * np.sum(steps ** 2),
                                               rel=4 * np.sqrt(2.0 / N))


def test_the_chance_of_one_and_the_particles_a_share_needs() -> None:
    from experiments.loop_bound import chance_of_one, particles_for

    p = np.array([0.02, 0.001, 0.3, 0.0, 0.05])
    J = 37
    brute = [1.0 - np.prod(np.full(J, 1.0 - x)) for x in p]
    np.testing.assert_allclose(chance_of_one(p, J), brute, rtol=1e-12, atol=1e-15)
    assert particles_for(p, 0.8) == float("inf")  # a seed in five with p = 0: J -> inf
    assert particles_for(p, 0.7) < float("inf")
    p = p[p > 0]
    J80 = particles_for(p, 0.8)
    assert np.mean(chance_of_one(p, J80)) == pytest.approx(0.8, abs=1e-9)
    assert np.mean(chance_of_one(p, 0.99 * J80)) < 0.8
    assert particles_for(np.array([1.0, 1.0]), 0.8) == 1.0


def test_the_bound_end_to_end_on_a_small_circle(tmp_path, capsys) -> None:
    """A 40 m circle, one seed: the approach frame is loop_closure's, and the share within
    1 m is a probability; the summary names the J that reaches 80 %."""
    from experiments.loop_bound import main
    from experiments.loop_closure import approach_frame
    from experiments.loop_paths import START_M, circle_loop
    from gslam_jax.config import Config
    from gslam_jax.datasets.sim_path import drive_path
    from gslam_jax.evaluation import loops
    from gslam_jax.vo.localmap import localmap_params

    out, png = tmp_path / "bound.json", tmp_path / "bound.png"
    assert main(["--circles", "40", "--seeds", "0", "--draws", "500", "--particles", "20",
                 "--course", "mars-yard-a", "--json", str(out), "--plot", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "mean chance of a particle within 1 m at the approach J=20" \
        in capsys.readouterr().out
    got = json.loads(out.read_text())
    (row,) = got["rows"]
    assert 0.0 <= row["p_within"] <= 1.0 and row["draws"] == 500
    truth = drive_path(circle_loop(tmp_path, 40.0, 20.0).file, 0, "mars-yard-a").trajectory.poses
    revisit = loops.find_revisit(truth, START_M, 20.0)
    reach = localmap_params(Config()).max_range
    assert row["approach_frame"] == approach_frame(truth, revisit, reach)
    s = got["summary"]["circle-40"]
    assert s["seeds"] == 1 and s["vo_miss_median_m"] == row["vo_miss_m"]
    assert s["spread_m"] == row["spread_m"] > 0.0 and 0.0 <= row["p_gauss"] <= 1.0
    assert row["p_gauss"] <= row["p_best_scale"] <= 1.0 and row["best_scale"] >= 0.0


def test_the_prediction_is_set_beside_the_filters_runs() -> None:
    """``against_runs``: per (proposal, J) the mean predicted chance and count against the
    share of runs with a particle within 1 m and their mean count, by hand; runs of a loop or
    seed without a bound, and runs that recorded no cloud, are left out."""
    from experiments.loop_bound import against_runs, chance_of_one

    bounds = [{"loop": "a", "seed": 0, "p_within": 0.01}, {"loop": "a", "seed": 1,
              "p_within": 0.0}, {"loop": "b", "seed": 0, "note": "no revisit"}]
    run = {"loop": "a", "proposal": "motion", "particles": 200, "closed": True}
    runs = [dict(run, seed=0, approach_within_1m=3), dict(run, seed=1, approach_within_1m=0),
            dict(run, seed=2, approach_within_1m=5), dict(run, seed=0, loop="b",
            approach_within_1m=1), dict(run, seed=0, particles=20)]
    got = against_runs(bounds, runs)
    assert list(got) == ["motion J=200"]
    c = got["motion J=200"]
    assert c["runs"] == 2 and c["had_one"] == 0.5 and c["count"] == 1.5
    assert c["chance"] == pytest.approx(chance_of_one(0.01, 200) / 2)
    assert c["expected"] == pytest.approx(1.0)


def test_the_gaussian_fit_gives_the_mass_within_the_radius() -> None:
    """``gaussian_within`` fitted to points drawn from a Gaussian: centred or not, the mass of
    the disc against the noncentral chi-square law (isotropic) and against SciPy's quadrature of
    the density over the disc (an elongated, turned cloud)."""
    from scipy import integrate, stats

    from experiments.loop_bound import gaussian_within

    rng = np.random.default_rng(0)
    for sigma, offset in [(0.5, 0.0), (0.5, 0.7), (3.0, 2.0), (20.0, 30.0)]:
        xy = rng.normal(0.0, sigma, (200000, 2))
        exact = stats.ncx2.cdf(1.0 / sigma ** 2, df=2, nc=offset ** 2 / sigma ** 2)
        got = gaussian_within(xy.mean(0), np.cov(xy.T), np.array([offset, 0.0]), 1.0)
        assert got == pytest.approx(exact, rel=0.02)
    cov = np.array([[4.0, 1.5], [1.5, 1.0]])
    xy = rng.multivariate_normal([1.0, -1.0], cov, 400000)
    law = stats.multivariate_normal(xy.mean(0), np.cov(xy.T))
    target = np.array([2.0, 0.5])
    exact, _ = integrate.dblquad(
        lambda r, a: law.pdf(target + r * np.array([np.cos(a), np.sin(a)])) * r,
        0.0, 2.0 * np.pi, 0.0, 1.5)
    assert gaussian_within(xy.mean(0), np.cov(xy.T), target, 1.5) == pytest.approx(exact,
                                                                                   rel=1e-3)


def test_the_best_width_for_a_seed_against_scipy() -> None:
    """``best_scaled_within``: for a round cloud the best width and its mass against SciPy's
    noncentral chi-square law maximised by SciPy's bounded search over the width, and against
    the far-truth closed form radius^2 / (e r^2) at width r / sqrt(2); for an elongated, turned
    cloud no factor on a fine grid gives more, and the cloud as fitted (k = 1) gives less."""
    from scipy import optimize, stats

    from experiments.loop_bound import best_scaled_within, gaussian_within

    for r, radius in [(2.0, 1.0), (6.8, 1.0), (22.0, 1.0), (9.0, 2.5)]:
        def minus_mass(log_sigma: float) -> float:
            s2 = np.exp(2.0 * log_sigma)
            return -stats.ncx2.cdf(radius ** 2 / s2, df=2, nc=r ** 2 / s2)

        ref = optimize.minimize_scalar(minus_mass, bounds=(-4.0, 6.0), method="bounded",
                                       options={"xatol": 1e-9})
        p, k = best_scaled_within(np.array([3.0, -1.0]), np.eye(2) * 4.0,
                                  np.array([3.0, r - 1.0]), radius)
        assert p == pytest.approx(-ref.fun, rel=1e-5)
        assert 2.0 * k == pytest.approx(np.exp(ref.x), rel=1e-3)  # the cloud's own sigma is 2
        if r / radius > 5:
            assert p == pytest.approx(radius ** 2 / (np.e * r ** 2), rel=0.03)
            assert 2.0 * k == pytest.approx(r / np.sqrt(2.0), rel=0.03)
    mean, cov, target = np.array([1.0, 2.0]), np.array([[30.0, 12.0], [12.0, 9.0]]), \
        np.array([9.0, -4.0])
    p, k = best_scaled_within(mean, cov, target, 1.0)
    grid = [gaussian_within(mean, x * x * cov, target, 1.0) for x in np.geomspace(0.1, 10, 2001)]
    assert p >= max(grid) * (1 - 1e-9) and p == pytest.approx(max(grid), rel=1e-4)
    assert gaussian_within(mean, cov, target, 1.0) < p
    assert best_scaled_within(mean, cov, mean + 0.5, 1.0) == (1.0, 0.0)  # the truth inside


def test_the_largest_miss_a_share_allows_against_scipy() -> None:
    """``largest_miss``: at the distance it returns, the best round cloud (SciPy's noncentral
    chi-square maximised over the width by SciPy) gives J particles the share's chance of one
    within the radius, and a little further out less; near the far-truth closed form."""
    from scipy import optimize, stats

    from experiments.loop_bound import chance_of_one, largest_miss

    def best_chance(r: float, J: int, radius: float) -> float:
        ref = optimize.minimize_scalar(
            lambda ls: -stats.ncx2.cdf(radius ** 2 / np.exp(2 * ls), df=2,
                                       nc=r ** 2 / np.exp(2 * ls)),
            bounds=(-4.0, 6.0), method="bounded", options={"xatol": 1e-9})
        return float(chance_of_one(-ref.fun, J))

    for J, share, radius in [(200, 0.8, 1.0), (2000, 0.8, 1.0), (20, 0.5, 2.0)]:
        r = largest_miss(J, share, radius)
        assert best_chance(r, J, radius) == pytest.approx(share, abs=1e-4)
        assert best_chance(1.02 * r, J, radius) < share
        p = 1.0 - (1.0 - share) ** (1.0 / J)
        assert r == pytest.approx(radius / np.sqrt(np.e * p), rel=0.03)
    assert largest_miss(200) == pytest.approx(6.8, abs=0.05)


def test_the_cloud_round_a_loop_grows_as_its_length_to_the_three_halves() -> None:
    """Heading noise alone (eq. 3's per-metre term) round circles of 200 m and 400 m walked in
    the same steps: the heading's variance grows as the length L, and every step's heading
    error moves the end by its lever arm (of order L), so the end's position covariance grows
    as L^3 and the area of the cloud (sqrt det) eightfold. The chance of a particle within
    1 m then falls as L^-3, and the particles a loop needs grow as L^3."""
    from experiments.loop_bound import motion_draws

    def cloud(length: float, step: float = 0.5, draws: int = 8000) -> float:
        T = int(round(length / step))
        controls = np.tile([step, 0.0, 2 * np.pi / T], (T, 1))
        pose = np.asarray(motion_draws(jax.random.key(3), jnp.zeros(3), controls,
                                       np.zeros(T, bool), MotionParams(0.0, 0.01, 0.0), draws),
                          np.float64)
        return float(np.sqrt(np.linalg.det(np.cov(pose[:, :2].T))))

    # the sample covariance's determinant of 8000 draws: a few per cent
    assert cloud(400.0) / cloud(200.0) == pytest.approx(8.0, rel=0.08)


def test_a_loops_summary_over_its_seeds_by_hand() -> None:
    from experiments.loop_bound import chance_of_one, summarise

    rows = [{"length_m": 800.0, "p_within": p, "p_gauss": g, "p_best_scale": b,
             "spread_m": sp, "vo_miss_m": m}
            for p, g, b, sp, m in [(0.01, 0.012, 0.02, 7.0, 5.0), (0.0, 1e-5, 4e-4, 8.0, 30.0),
                                   (0.002, 0.003, 0.004, 6.0, 9.0)]]
    s = summarise(rows, [200])
    assert (s["length_m"], s["seeds"], s["spread_m"], s["vo_miss_median_m"]) == (800.0, 3, 7.0,
                                                                                   9.0)
    assert s["chance"][200] == pytest.approx(np.mean([chance_of_one(p, 200)
                                                      for p in (0.01, 0.0, 0.002)]))
    assert s["chance_gauss"][200] == pytest.approx(np.mean([chance_of_one(g, 200)
                                                            for g in (0.012, 1e-5, 0.003)]))
    assert s["chance_best_scale"][200] == pytest.approx(
        np.mean([chance_of_one(b, 200) for b in (0.02, 4e-4, 0.004)]))
    assert s["particles_for_share"] == float("inf")  # a seed in three with p = 0
    assert s["particles_for_share_gauss"] < float("inf")
