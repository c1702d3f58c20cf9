"""Figures of a run (matplotlib, Agg backend): variance maps like the paper's Figs. 5-11, the
VO-only map beside the Gamma-SLAM map, and the effective sample size over frames (Fig. 4, top).

Map inputs are expected-std arrays [Nx, Ny] (axis 0 is x, NaN = unknown), the world position of
cell (0, 0)'s corner and the cell side, as in ``gridmap.GridMap``. Colours: dark = flat,
bright = tall/rough, on a log scale; unknown cells are drawn in a muted blue-grey.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import LogNorm  # noqa: E402

__all__ = ["draw_map", "save_map_png", "save_map_comparison_png", "save_ground_truth_png",
           "save_ess_png", "save_maps_png"]

_UNKNOWN = (0.16, 0.19, 0.24)
_STD_RANGE = (0.01, 1.0)  # metres: sand .. walls


def draw_map(ax: plt.Axes, std: np.ndarray, origin: Sequence[float], resolution: float,
             path: np.ndarray | None = None, title: str | None = None,
             std_range: tuple[float, float] = _STD_RANGE, cmap: str = "inferno"):
    """Draw one expected-std map (and a path [T, >=2] in white) on ``ax``; returns the image."""
    std = np.asarray(std, dtype=np.float64)
    if std.ndim != 2:
        raise ValueError(f"std must be a 2-D [Nx, Ny] array, got shape {std.shape}")
    if not resolution > 0:
        raise ValueError(f"resolution must be positive, got {resolution}")
    x0, y0 = float(origin[0]), float(origin[1])
    extent = (x0, x0 + std.shape[0] * resolution, y0, y0 + std.shape[1] * resolution)
    colormap = matplotlib.colormaps[cmap].with_extremes(bad=_UNKNOWN)
    shown = np.ma.masked_invalid(np.clip(std, *std_range))
    im = ax.imshow(shown.T, origin="lower", extent=extent, cmap=colormap,
                   norm=LogNorm(*std_range), interpolation="nearest")
    if path is not None:
        path = np.asarray(path)
        ax.plot(path[:, 0], path[:, 1], color="white", lw=0.8, alpha=0.9)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    if title:
        ax.set_title(title)
    return im


def save_map_png(out: str | Path, std: np.ndarray, origin: Sequence[float], resolution: float,
                 path: np.ndarray | None = None, title: str | None = None, dpi: int = 120) -> Path:
    """One map, coloured by expected standard deviation, with the path drawn."""
    out = Path(out)
    std = np.asarray(std)
    w, h = _figsize(std.shape, 1)
    fig, ax = plt.subplots(figsize=(w, h))
    im = draw_map(ax, std, origin, resolution, path, title)
    window = _data_window(std, origin, resolution)
    if window is not None:
        ax.set_xlim(window[0], window[1])
        ax.set_ylim(window[2], window[3])
    fig.colorbar(im, ax=ax, label="expected std of heights (m)", shrink=0.8)
    fig.tight_layout()
    fig.savefig(out, dpi=dpi)
    plt.close(fig)
    return out


def save_map_comparison_png(out: str | Path, vo_std: np.ndarray, vo_origin: Sequence[float],
                            slam_std: np.ndarray, slam_origin: Sequence[float], resolution: float,
                            vo_path: np.ndarray | None = None,
                            slam_path: np.ndarray | None = None,
                            titles: tuple[str, str] = ("VO only", "Gamma-SLAM"),
                            suptitle: str | None = None, dpi: int = 120) -> Path:
    """The VO-only map beside the SLAM map (paper Figs. 5, 6, 8, 9, 11), same colour scale."""
    out = Path(out)
    shape = (max(vo_std.shape[0], slam_std.shape[0]), max(vo_std.shape[1], slam_std.shape[1]))
    w, h = _figsize(shape, 2)
    fig, axes = plt.subplots(1, 2, figsize=(w, h))
    draw_map(axes[0], vo_std, vo_origin, resolution, vo_path, titles[0])
    im = draw_map(axes[1], slam_std, slam_origin, resolution, slam_path, titles[1])
    # one common window around the known cells, so both panels show the same place and scale
    windows = [w for w in (_data_window(vo_std, vo_origin, resolution),
                           _data_window(slam_std, slam_origin, resolution)) if w is not None]
    if windows:
        box = np.array(windows)
        for ax in axes:
            ax.set_xlim(box[:, 0].min(), box[:, 1].max())
            ax.set_ylim(box[:, 2].min(), box[:, 3].max())
    fig.colorbar(im, ax=list(axes), label="expected std of heights (m)", shrink=0.8)
    if suptitle:
        fig.suptitle(suptitle)
    fig.savefig(out, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return out


def save_ground_truth_png(out: str | Path, vo_std: np.ndarray, vo_origin: Sequence[float],
                          slam_std: np.ndarray, slam_origin: Sequence[float], resolution: float,
                          ground_truth: np.ndarray, vo_path: np.ndarray, slam_path: np.ndarray,
                          dpi: int = 120) -> Path:
    """The VO-only and Gamma-SLAM maps with their paths (white) and the ground truth (cyan,
    dashed) over both, in the maps' frame (``metrics.ground_truth_in_map_frame``): where a
    path leaves the truth, the map built along it is displaced as much."""
    out = Path(out)
    gt = np.asarray(ground_truth, np.float64)
    if gt.ndim != 2 or gt.shape[1] < 2:
        raise ValueError(f"ground_truth must be [T, >=2], got shape {gt.shape}")
    shape = (max(vo_std.shape[0], slam_std.shape[0]), max(vo_std.shape[1], slam_std.shape[1]))
    w, h = _figsize(shape, 2)
    fig, axes = plt.subplots(1, 2, figsize=(w, h))
    draw_map(axes[0], vo_std, vo_origin, resolution, vo_path, "VO only")
    im = draw_map(axes[1], slam_std, slam_origin, resolution, slam_path, "Gamma-SLAM")
    windows = [w for w in (_data_window(vo_std, vo_origin, resolution),
                           _data_window(slam_std, slam_origin, resolution)) if w is not None]
    for ax in axes:
        ax.plot(gt[:, 0], gt[:, 1], color="cyan", ls="--", lw=1.0, label="ground truth")
        ax.plot([], [], color="white", lw=0.8, label="estimate")
        ax.legend(loc="best", fontsize=8, facecolor=_UNKNOWN, labelcolor="white")
        if windows:
            box = np.array(windows)
            ax.set_xlim(box[:, 0].min(), box[:, 1].max())
            ax.set_ylim(box[:, 2].min(), box[:, 3].max())
    fig.colorbar(im, ax=list(axes), label="expected std of heights (m)", shrink=0.8)
    fig.suptitle("Ground truth over the maps and paths")
    fig.savefig(out, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return out


def save_ess_png(out: str | Path, ess: np.ndarray, num_particles: int,
                 frames: np.ndarray | None = None, resampled: np.ndarray | None = None,
                 threshold: float | None = 0.5, title: str | None = None, dpi: int = 120) -> Path:
    """Effective number of particles over frames (paper Fig. 4, top), resampling marked."""
    out = Path(out)
    ess = np.asarray(ess, dtype=np.float64)
    x = np.arange(ess.size) if frames is None else np.asarray(frames)
    if x.shape != ess.shape:
        raise ValueError(f"frames {x.shape} and ess {ess.shape} differ in shape")
    fig, ax = plt.subplots(figsize=(8, 3))
    ax.plot(x, ess, lw=1.0, color="tab:blue", label="effective particles")
    if threshold is not None:
        ax.axhline(threshold * num_particles, color="grey", ls="--", lw=0.8,
                   label=f"resampling threshold ({threshold:g} J)")
    if resampled is not None:
        r = np.asarray(resampled, dtype=bool)
        ax.plot(x[r], ess[r], "v", color="tab:red", ms=4, label="resampled")
    ax.set_ylim(0, num_particles * 1.05)
    ax.set_xlabel("frame")
    ax.set_ylabel("J_eff")
    ax.set_title(title or f"Effective number of particles (J = {num_particles})")
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=dpi)
    plt.close(fig)
    return out


def _data_window(std: np.ndarray, origin: Sequence[float], resolution: float,
                 margin: float = 2.0) -> tuple[float, float, float, float] | None:
    """(x0, x1, y0, y1) around the known (finite) cells plus ``margin`` metres; None if none."""
    known = np.isfinite(np.asarray(std))
    if not known.any():
        return None
    i = np.flatnonzero(known.any(axis=1))
    j = np.flatnonzero(known.any(axis=0))
    x0, y0 = float(origin[0]), float(origin[1])
    return (x0 + i[0] * resolution - margin, x0 + (i[-1] + 1) * resolution + margin,
            y0 + j[0] * resolution - margin, y0 + (j[-1] + 1) * resolution + margin)


def _figsize(shape: tuple[int, ...], panels: int) -> tuple[float, float]:
    if len(shape) != 2:
        raise ValueError(f"std must be a 2-D [Nx, Ny] array, got shape {shape}")
    aspect = shape[1] / max(shape[0], 1)  # height / width of one panel
    width = 6.5 * panels
    return width + 1.5, float(np.clip(6.5 * aspect, 2.5, 10.0)) + 0.8


def save_maps_png(out: str | Path, panels: Sequence[tuple[str, np.ndarray, Sequence[float],
                                                           np.ndarray | None]],
                  resolution: float, suptitle: str | None = None, dpi: int = 120) -> Path:
    """Maps side by side in one frame and one window, same colour scale: panels of (title,
    expected std [Nx, Ny], origin, path [T, >=2] or None), e.g. run A, run B placed in A's
    frame, and their merge."""
    out = Path(out)
    shape = (max(p[1].shape[0] for p in panels), max(p[1].shape[1] for p in panels))
    w, h = _figsize(shape, len(panels))
    fig, axes = plt.subplots(1, len(panels), figsize=(w, h), squeeze=False)
    axes = list(axes[0])
    im = None
    for ax, (title, std, origin, path) in zip(axes, panels):
        im = draw_map(ax, std, origin, resolution, path, title)
    windows = [w for w in (_data_window(p[1], p[2], resolution) for p in panels) if w]
    if windows:
        box = np.array(windows)
        for ax in axes:
            ax.set_xlim(box[:, 0].min(), box[:, 1].max())
            ax.set_ylim(box[:, 2].min(), box[:, 3].max())
    fig.colorbar(im, ax=axes, label="expected std of heights (m)", shrink=0.8)
    if suptitle:
        fig.suptitle(suptitle)
    fig.savefig(out, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return out
