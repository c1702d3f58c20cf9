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
