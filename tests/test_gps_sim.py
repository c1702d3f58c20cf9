"""Simulated WAAS-like receiver; end-to-end GPS alignment accuracy; georeferenced outputs."""

from __future__ import annotations

import numpy as np
import pytest

from gslam_jax import gps
from gslam_jax.gps import simulate as gps_sim


def _course(dt: float = 0.1, speed: float = 1.0,
            laps: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """A rounded 150 m x 80 m loop driven ``laps`` times: times [T], poses [T,3]."""
    th = np.linspace(0, 2 * np.pi, 4001)
    c, s = np.cos(th), np.sin(th)
    pts = np.stack([75 * np.sign(c) * np.abs(c) ** 0.3, 40 * np.sign(s) * np.abs(s) ** 0.3], -1)
    arc = np.r_[0, np.cumsum(np.hypot(*np.diff(pts, axis=0).T))]
    u = np.arange(0, laps * arc[-1], speed * dt)
    x, y = np.interp(u % arc[-1], arc, pts[:, 0]), np.interp(u % arc[-1], arc, pts[:, 1])
    heading = np.unwrap(np.arctan2(np.gradient(y), np.gradient(x)))
    return u / speed, np.stack([x, y, heading], -1)


def _rot(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def test_receiver_statistics_and_seeding():
    t = np.arange(0, 20000.0, 1.0)
    poses = np.zeros((t.size, 3))
    cfg = gps_sim.GpsSimConfig()
    sim = gps_sim.simulate_gps(np.random.default_rng(0), poses, t, cfg)
    e, epe = sim.error_xy, sim.log.epe
    assert epe.min() >= 3.0 and epe.max() <= 10.0
    rms = np.sqrt(np.mean(np.sum(e**2, -1)))
    assert 3.0 < rms < 10.0
    np.testing.assert_allclose(rms / np.sqrt(np.mean(epe**2)), 1.0, atol=0.15)
    rho = np.corrcoef(e[:-1, 0], e[1:, 0])[0, 1]  # first-order Gauss-Markov, tau = 30 s
    assert abs(rho - np.exp(-1 / cfg.error_tau)) < 0.02
    again = gps_sim.simulate_gps(np.random.default_rng(0), poses, t, cfg)
    np.testing.assert_array_equal(again.log.xy, sim.log.xy)
    other = gps_sim.simulate_gps(np.random.default_rng(1), poses, t, cfg)
    assert not np.allclose(other.log.xy, sim.log.xy)
    dropped = gps_sim.simulate_gps(np.random.default_rng(0), poses[:1000], t[:1000],
                                   cfg._replace(dropout=0.2))
    assert dropped.log.n_skipped + dropped.log.time.size == 1000
    assert 150 < dropped.log.n_skipped < 250


def test_simulated_log_round_trips_through_csv(tmp_path):
    t, poses = _course(laps=0.3)
    sim = gps_sim.simulate_gps(np.random.default_rng(2), poses, t)
    path = tmp_path / "sim_gps.csv"
    gps.write_gps_log(path, sim.log.time, sim.log.lat, sim.log.lon, sim.log.epe)
    log = gps.read_gps_log(path, origin=sim.log.origin)
    assert log.zone == sim.log.zone and log.n_skipped == 0
    np.testing.assert_allclose(log.xy, sim.log.xy, atol=1e-3)   # 1e-9 deg in the file
    np.testing.assert_allclose(log.epe, sim.log.epe, atol=1e-3)


def test_aligned_slam_beats_raw_gps_on_simulated_course():
    t, poses = _course(laps=3.0)               # 1380 s, three laps, 10 Hz
    theta, offset = 0.7, np.array([120.0, -40.0])
    cfg = gps_sim.GpsSimConfig(frame_rotation=theta, frame_offset=tuple(offset))
    truth = poses[:, :2] @ _rot(theta).T + offset
    raw, aligned_err = [], []
    for seed in range(6):
        rng = np.random.default_rng(seed)
        sim = gps_sim.simulate_gps(rng, poses, t, cfg)
        # Stand-in for a SLAM path: truth in the world frame + slow drift + jitter.
        drift = np.cumsum(rng.normal(0, 0.02 * np.sqrt(0.1), (t.size, 2)), 0)
        slam = poses[:, :2] + drift + rng.normal(0, 0.05, (t.size, 2))
        al, aligned = gps.align_to_gps(t, slam, sim.log.time, sim.log.xy, sim.log.epe)
        assert bool(al.ok) and int(al.n_used) == sim.log.time.size
        raw.append(np.sqrt(np.mean(np.sum(sim.error_xy**2, -1))))
        aligned_err.append(np.sqrt(np.mean(np.sum((np.asarray(aligned) - truth) ** 2, -1))))
        assert aligned_err[-1] < 0.6 * raw[-1], (seed, raw[-1], aligned_err[-1])
    raw, aligned_err = np.array(raw), np.array(aligned_err)
    print(f"raw GPS RMS {np.round(raw, 2)} m; aligned SLAM RMS {np.round(aligned_err, 2)} m")
    assert np.sqrt(np.mean(aligned_err**2)) < 0.4 * np.sqrt(np.mean(raw**2))


def test_particles_and_world_file(tmp_path):
    t, poses = _course(laps=0.5)
    sim = gps_sim.simulate_gps(np.random.default_rng(3), poses, t,
                               gps_sim.GpsSimConfig(frame_rotation=-1.2, frame_offset=(30, 60)))
    paths = np.stack([poses[:, :2], poses[:, :2] @ _rot(0.1).T + 5.0])  # two "particles"
    al, aligned = gps.align_to_gps(t, paths, sim.log.time, sim.log.xy, sim.log.epe)
    assert al.R.shape == (2, 2, 2) and aligned.shape == paths.shape
    th = np.arctan2(np.asarray(al.R[:, 1, 0]), np.asarray(al.R[:, 0, 0]))
    assert abs(th[0] - th[1] - 0.1) < 1e-4     # same fit up to each particle's own frame
    best = gps.Alignment(*(np.asarray(x[0]) for x in al))

    # Map corners and the world file agree with transform_points; PNG is north-up.
    origin, res, shape = (-100.0, -60.0), 0.5, (400, 240)
    corners = np.asarray(gps.transform_points(best, gps.map_corners(origin, res, shape)))
    site = sim.log.origin
    grid = np.full(shape, np.nan)
    grid[0, -1] = 1.0                          # cell (0, ny-1): north-west corner of the map
    grid[-1, 0] = 0.0
    png, pgw = gps.write_georeferenced_png(tmp_path / "map.png", grid, origin, res,
                                           best.R, best.l, site)
    A, D, B, E, C, F = np.loadtxt(pgw)
    if best.R[0, 0] > 0.99:
        pytest.fail("test needs a rotated alignment")
    img = __import__("matplotlib.image", fromlist=["imread"]).imread(png)
    assert img.shape[:2] == (shape[1], shape[0])
    assert img[0, 0, 3] > 0 and img[-1, -1, 3] > 0 and img[0, -1, 3] == 0  # NaN transparent
    for col, row in [(0, 0), (shape[0] - 1, shape[1] - 1), (17, 33)]:
        i, j = col, shape[1] - 1 - row
        centre = np.array([origin[0] + (i + 0.5) * res, origin[1] + (j + 0.5) * res])
        want = np.asarray(gps.transform_points(best, centre), np.float64) + site
        np.testing.assert_allclose([A * col + B * row + C, D * col + E * row + F], want,
                                   atol=2e-3)
    # Pixel edges: the outer corner of the top-left pixel is the map's (x0, y0 + h) corner.
    np.testing.assert_allclose([C - 0.5 * (A + B), F - 0.5 * (D + E)], corners[3] + site,
                               atol=2e-3)
    np.testing.assert_allclose(np.hypot(A, D), res, rtol=1e-6)
