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
