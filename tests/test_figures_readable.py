"""The run's figures read well on the runs users bring (issue 68, "Figures and formats"): a
still vehicle's errors, a short run's ESS, KITTI's long thin maps."""

from __future__ import annotations

import numpy as np
import pytest

from gslam_jax.app import plots


@pytest.fixture
def figures(monkeypatch):
    """The figures the plot functions save, kept open for inspection (closed at the end)."""
    kept = []
    close = plots.plt.close
    monkeypatch.setattr(plots.plt, "close", lambda fig=None: kept.append(fig))
    yield kept
    for fig in kept:
        close(fig)


def test_errors_of_a_still_vehicle_on_a_sensible_axis(tmp_path, figures):
    T = 50
    gt = np.zeros((T, 3))
    gt[:, 0] = np.linspace(0, 0.002, T)  # 2 mm of creep: a static clip
    rng = np.random.default_rng(0)
    est = gt + np.column_stack([rng.normal(0, 3e-4, (T, 2)), np.zeros(T)])
    plots.save_errors_png(tmp_path / "errors.png", gt, [("VO only", est)])
    (fig,) = figures
    ax = fig.axes[0]
    assert ax.get_ylim()[0] == 0 and ax.get_ylim()[1] >= plots.MIN_ERROR_SPAN
    (label,) = [t.get_text() for t in ax.get_legend().get_texts()]
    assert label.endswith(" mm)") and "0.000" not in label and "0.001 m" not in label


def test_errors_of_a_moving_vehicle_keep_their_scale(tmp_path, figures):
    T = 50
    gt = np.column_stack([np.linspace(0, 100, T), np.zeros(T), np.zeros(T)])
    est = gt.copy()
    est[:, 1] = 3.0 * np.sin(np.linspace(0, 2 * np.pi, T))  # metres of error, no rigid fit
    plots.save_errors_png(tmp_path / "errors.png", gt, [("VO only", est)])
    ax = figures[0].axes[0]
    assert ax.get_ylim()[1] >= 1.0
    assert ax.get_legend().get_texts()[0].get_text().endswith(" m)")


def test_ess_of_a_short_run_has_whole_frame_ticks_and_no_unhappened_resampling(tmp_path,
                                                                               figures):
    ess = np.array([20.0, 19.5, 19.0, 18.7])
    plots.save_ess_png(tmp_path / "ess.png", ess, 20, resampled=np.zeros(4, bool))
    ax = figures[0].axes[0]
    ticks = [t for t in ax.get_xticks() if ax.get_xlim()[0] <= t <= ax.get_xlim()[1]]
    assert ticks and all(float(t).is_integer() for t in ticks)
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert not any("resampled" in s for s in labels)


def test_ess_names_the_resamplings_when_there_are_some(tmp_path, figures):
    r = np.zeros(30, bool)
    r[[5, 17]] = True
    plots.save_ess_png(tmp_path / "ess.png", np.full(30, 10.0), 20, resampled=r)
    labels = [t.get_text() for t in figures[0].axes[0].get_legend().get_texts()]
    assert "resampled (2 times)" in labels


def _strip(seed: int = 0):
    """A KITTI-like strip: 160 m of road 8 m wide, the path starting behind the first cell
    the cameras saw, and the ground truth beside it."""
    rng = np.random.default_rng(seed)
    std = np.full((1100, 70), np.nan)
    std[40:1000, 10:60] = np.exp(rng.uniform(np.log(0.01), np.log(1.0), (960, 50)))
    x = np.linspace(-1.0, 160.0, 300)
    path = np.stack([x, 5 + 0.3 * np.sin(x / 20), 0 * x], 1)
    return std, path


def _inside(ax, xy) -> bool:
    (x0, x1), (y0, y1) = sorted(ax.get_xlim()), sorted(ax.get_ylim())
    return x0 < xy[0] < x1 and y0 < xy[1] < y1


def _overlap(a, b) -> bool:
    return a.x0 < b.x1 and b.x0 < a.x1 and a.y0 < b.y1 and b.y0 < a.y1


def test_a_strip_map_keeps_its_marks_and_legend_clear(tmp_path, figures):
    std, path = _strip()
    out = plots.save_map_png(tmp_path / "map.png", std, (-5.0, 0.0), 0.16, path, "strip",
                             path_label="Gamma-SLAM path")
    (fig,) = figures
    ax = fig.axes[0]
    assert _inside(ax, path[0]) and _inside(ax, path[-1])  # start and end marks not clipped
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    legend = ax.get_legend().get_window_extent(renderer)
    assert not _overlap(legend, ax.get_window_extent(renderer))  # the legend is outside
    # the panel is tall enough to read, and the image not a sliver
    assert ax.get_window_extent(renderer).height >= 0.8 * plots.MIN_PANEL_INCHES * fig.dpi
    from matplotlib.image import imread
    h, w = imread(out).shape[:2]
    assert h >= 400 and w >= 1000


def test_strip_panels_are_stacked_and_the_truth_is_drawn_apart_from_the_path(tmp_path,
                                                                            figures):
    std, path = _strip()
    truth = path + [0.0, 0.2, 0.0]
    plots.save_ground_truth_png(tmp_path / "gt.png", std, (-5.0, 0.0), std, (-5.0, 0.0), 0.16,
                                truth, path, path)
    (fig,) = figures
    maps = [ax for ax in fig.axes if ax.get_images()]
    assert len(maps) == 2
    fig.canvas.draw()
    boxes = [ax.get_window_extent() for ax in maps]
    assert boxes[0].y0 > boxes[1].y1  # one above the other, not side by side
    for ax in maps:
        lines = {line.get_label(): line for line in ax.get_lines()}
        truth_line = lines["ground truth"]
        path_line = next(v for k, v in lines.items() if k.endswith("path"))
        assert truth_line.get_color() != path_line.get_color()
        assert truth_line.get_linewidth() >= 2 * path_line.get_linewidth()
        assert truth_line.get_linestyle() != path_line.get_linestyle()
        assert path_line.get_zorder() > truth_line.get_zorder()  # the thin path on top
        assert _inside(ax, path[0]) and _inside(ax, path[-1])


def test_a_square_map_keeps_panels_side_by_side_with_legends_outside(tmp_path, figures):
    rng = np.random.default_rng(1)
    std = np.exp(rng.uniform(np.log(0.01), np.log(1.0), (200, 180)))
    path = np.stack([np.linspace(1, 30, 40), np.linspace(1, 25, 40)], 1)
    plots.save_map_comparison_png(tmp_path / "cmp.png", std, (0, 0), std, (0, 0), 0.16,
                                  path, path)
    (fig,) = figures
    maps = [ax for ax in fig.axes if ax.get_images()]
    fig.canvas.draw()
    a, b = (ax.get_window_extent() for ax in maps)
    assert b.x0 > a.x1  # side by side
    for ax in maps:
        assert not _overlap(ax.get_legend().get_window_extent(), ax.get_window_extent())
