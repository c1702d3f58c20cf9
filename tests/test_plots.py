"""Figures are written, readable, and refuse malformed input."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.image import imread

from gslam_jax.app.plots import save_ess_png, save_map_comparison_png, save_map_png


def _std_map(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    std = np.exp(rng.uniform(np.log(0.01), np.log(1.0), (80, 50)))
    std[:10] = np.nan
    return std


def test_map_png(tmp_path) -> None:
    path = np.stack([np.linspace(1, 10, 50), np.linspace(1, 5, 50)], axis=1)
    out = save_map_png(tmp_path / "map.png", _std_map(0), (0.0, 0.0), 0.16, path, "test")
    img = imread(out)
    assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100
    assert img[..., :3].std() > 0.05  # not a blank canvas


def test_comparison_and_ess_png(tmp_path) -> None:
    a = save_map_comparison_png(tmp_path / "cmp.png", _std_map(1), (0.0, 0.0), _std_map(2),
                                (-1.0, 0.5), 0.16, np.zeros((3, 3)), np.ones((3, 3)))
    assert imread(a).shape[1] > imread(a).shape[0]  # side by side
    ess = np.linspace(200, 60, 300)
    resampled = np.zeros(300, bool)
    resampled[[100, 250]] = True
    b = save_ess_png(tmp_path / "ess.png", ess, 200, resampled=resampled)
    assert imread(b).size > 0


def test_bad_inputs(tmp_path) -> None:
    with pytest.raises(ValueError, match="std"):
        save_map_png(tmp_path / "x.png", np.zeros(5), (0, 0), 0.16)
    with pytest.raises(ValueError, match="resolution"):
        save_map_png(tmp_path / "x.png", np.zeros((5, 5)), (0, 0), 0.0)
    with pytest.raises(ValueError, match="frames"):
        save_ess_png(tmp_path / "x.png", np.ones(5), 10, frames=np.arange(4))


def test_ground_truth_png(tmp_path) -> None:
    from gslam_jax.app.plots import save_ground_truth_png

    gt = np.stack([np.linspace(1, 10, 20), np.linspace(1, 5, 20), np.zeros(20)], axis=1)
    gt[3] = np.nan  # a frame without ground truth is a gap in the line, not an error
    out = save_ground_truth_png(tmp_path / "gt.png", _std_map(1), (0.0, 0.0), _std_map(2),
                                (0.0, 0.0), 0.16, gt, gt + 0.2, gt - 0.2)
    img = imread(out)
    assert img.shape[1] > img.shape[0]
    # the ground truth's cyan is drawn: pixels with little red, much green and blue
    rgb = img[..., :3]
    assert np.sum((rgb[..., 0] < 0.2) & (rgb[..., 1] > 0.8) & (rgb[..., 2] > 0.8)) > 20
    with pytest.raises(ValueError, match="ground_truth"):
        save_ground_truth_png(tmp_path / "x.png", _std_map(1), (0, 0), _std_map(1), (0, 0),
                              0.16, np.zeros(5), gt, gt)


def test_every_map_figure_and_errors_png_written(tmp_path) -> None:
    from gslam_jax.app.plots import save_errors_png, save_ground_truth_png, save_maps_png

    gt = np.stack([np.linspace(1, 10, 20), np.linspace(1, 5, 20), np.zeros(20)], axis=1)
    outs = [
        save_map_png(tmp_path / "map.png", _std_map(0), (0.0, 0.0), 0.16, gt),
        save_map_comparison_png(tmp_path / "cmp.png", _std_map(1), (0.0, 0.0), _std_map(2),
                                (0.0, 0.0), 0.16, gt + 0.2, gt),
        save_ground_truth_png(tmp_path / "gt.png", _std_map(1), (0.0, 0.0), _std_map(2),
                              (0.0, 0.0), 0.16, gt, gt + 0.2, gt - 0.2),
        save_maps_png(tmp_path / "merge.png", [("A", _std_map(1), (0.0, 0.0), gt),
                                               ("merged", _std_map(2), (0.0, 0.0), None)], 0.16),
        save_ess_png(tmp_path / "ess.png", np.linspace(20, 6, 30), 20),
        save_errors_png(tmp_path / "errors.png", gt, [("VO only", gt + 0.1), ("SLAM", gt)]),
    ]
    for out in outs:
        assert out.stat().st_size > 0 and imread(out)[..., :3].std() > 0.01, out.name


def test_map_legend_names_lines_marks_and_unobserved() -> None:
    import matplotlib.pyplot as plt

    from gslam_jax.app.plots import draw_line, draw_map, map_legend

    fig, ax = plt.subplots()
    path = np.stack([np.linspace(1, 10, 20), np.linspace(1, 5, 20)], axis=1)
    draw_map(ax, _std_map(0), (0.0, 0.0), 0.16, path, "t", path_label="VO path")
    draw_line(ax, path + 1, "ground truth", color="cyan")
    map_legend(ax, _std_map(0))
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ["VO path", "ground truth", "start", "end", "unobserved"]
    full = np.ones((4, 4))  # every cell observed: no "unobserved" entry
    ax.clear()
    draw_map(ax, full, (0.0, 0.0), 0.16, path, path_label="VO path")
    map_legend(ax, full)
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["VO path", "start", "end"]
    plt.close(fig)


def test_error_along_distance_hand_built() -> None:
    """A straight truth at x = -3, -1, 1, 3 and an estimate off by +d, -d, -d, +d across it
    (moved by an arbitrary rigid motion): the offsets have zero mean and zero moment along the
    line, so the best fit leaves every error at d. A frame without ground truth is skipped and
    the distance bridges it."""
    from gslam_jax.app.plots import error_along_distance

    d = 0.25
    x = np.array([-3.0, -1.0, 1.0, 3.0])
    gt = np.stack([x, np.zeros(4), np.zeros(4)], axis=1)
    est = gt.copy()
    est[:, 1] = d * np.array([1, -1, -1, 1])
    a = 0.7
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    est[:, :2] = est[:, :2] @ rot.T + [5.0, -2.0]
    gt = np.insert(gt, 2, np.nan, axis=0)  # frame 2 has no ground truth
    est = np.insert(est, 2, [100.0, 100.0, 0.0], axis=0)  # and its estimate must not count
    distance, error = error_along_distance(gt, est)
    np.testing.assert_allclose(distance, [0.0, 2.0, 4.0, 6.0], atol=1e-12)
    np.testing.assert_allclose(error, d, atol=1e-12)
    assert error_along_distance(gt[:1], est[:1])[0].size == 0  # fewer than 2 known frames


def test_error_along_distance_against_brute_force() -> None:
    """The errors are those of the rigid motion minimising the summed squared error (found by
    SciPy from scratch), and their RMS is the summary's RMS."""
    from scipy.optimize import minimize

    from gslam_jax.app.plots import error_along_distance
    from gslam_jax.evaluation.metrics import errors_over_known_frames

    rng = np.random.default_rng(3)
    t = np.linspace(0, 2 * np.pi, 25)
    gt = np.stack([6 * np.cos(t), 3 * np.sin(t), t], axis=1)
    est = gt + rng.normal(0, 0.3, gt.shape)
    est[:, :2] = est[:, :2] @ np.array([[0.0, -1.0], [1.0, 0.0]]).T + 4.0
    gt[[5, 6, 17]] = np.nan

    known = np.isfinite(gt[:, 0])

    def residuals(v):
        c, s = np.cos(v[0]), np.sin(v[0])
        moved = est[known, :2] @ np.array([[c, -s], [s, c]]).T + v[1:]
        return np.hypot(*(moved - gt[known, :2]).T)

    best = min((minimize(lambda v: np.sum(residuals(v) ** 2), [a0, 0.0, 0.0],
                         method="Nelder-Mead", options={"xatol": 1e-10, "fatol": 1e-14,
                                                        "maxiter": 20000})
                for a0 in np.linspace(-np.pi, np.pi, 8, endpoint=False)), key=lambda r: r.fun)
    distance, error = error_along_distance(gt, est)
    np.testing.assert_allclose(error, residuals(best.x), atol=1e-5)
    steps = np.hypot(*np.diff(gt[known, :2], axis=0).T)
    np.testing.assert_allclose(distance, np.r_[0.0, np.cumsum(steps)])
    rms = errors_over_known_frames({"vo": est}, gt)["vo_rms_m"]
    assert np.sqrt(np.mean(error ** 2)) == pytest.approx(rms, rel=1e-12)


def test_error_along_distance_refuses_mismatched_shapes() -> None:
    from gslam_jax.app.plots import error_along_distance

    with pytest.raises(ValueError, match="estimate"):
        error_along_distance(np.zeros((5, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="ground_truth"):
        error_along_distance(np.zeros(5), np.zeros((5, 3)))


def test_write_figures_writes_errors_png_only_with_ground_truth(tmp_path, monkeypatch) -> None:
    from types import SimpleNamespace

    from gslam_jax.app.outputs import write_figures
    from gslam_jax.gridmap import pose_maps
    from gslam_jax.gridmap.grid import GridMap

    rng = np.random.default_rng(0)
    k = np.where(rng.uniform(size=(40, 30)) < 0.8, 5.0, 0.0)
    grid = GridMap(k, k * 0.01, (-1.0, -1.0), 0.16)
    monkeypatch.setattr(pose_maps, "vo_only_map", lambda run: grid)
    path = np.stack([np.linspace(0, 4, 12), np.linspace(0, 2, 12), np.zeros(12)], axis=1)
    result = SimpleNamespace(kmap=grid.k, smap=grid.S, map_origin=grid.origin,
                             resolution=grid.resolution, map_heading=0.0, path=path,
                             vo_path=path + 0.05,
                             ess=np.linspace(10, 4, 12), resampled=np.zeros(12, bool))
    for name, gt in (("with", path + 0.01), ("without", None)):
        out = tmp_path / name
        out.mkdir()
        write_figures(out, SimpleNamespace(ground_truth=gt), result, 10)
        figures = {"map.png", "maps_vo_vs_slam.png", "ess.png"} | \
            ({"ground_truth.png", "errors.png"} if gt is not None else set())
        assert {p.name for p in out.iterdir()} == figures
        assert all((out / f).stat().st_size > 0 for f in figures)


def test_a_turned_lattice_is_drawn_turned() -> None:
    """A map whose lattice lies at a heading in its frame (``GridMap.heading``): the image is
    drawn through that rotation, and the window holds the turned known box."""
    import math

    import matplotlib.pyplot as plt

    from gslam_jax.app.plots import _data_window, draw_map

    std = np.full((10, 4), 0.1)
    heading, origin, res = 0.6, (1.0, -2.0), 0.5
    fig, ax = plt.subplots()
    im = draw_map(ax, std, (*origin, heading), res)
    u, v = origin[0] + 10 * res, origin[1] + 4 * res  # the lattice's far corner
    c, s = math.cos(heading), math.sin(heading)
    np.testing.assert_allclose(im.get_transform().transform([(u, v)]),
                               ax.transData.transform([(c * u - s * v, s * u + c * v)]))
    plt.close(fig)
    corners = [(x, y) for x in (origin[0], u) for y in (origin[1], v)]
    turned = np.array([(c * x - s * y, s * x + c * y) for x, y in corners])
    window = _data_window(std, (*origin, heading), res, margin=0.0)
    np.testing.assert_allclose(window, [turned[:, 0].min(), turned[:, 0].max(),
                                        turned[:, 1].min(), turned[:, 1].max()])
