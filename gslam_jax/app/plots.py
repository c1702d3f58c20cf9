"""Figures of a run (matplotlib, Agg backend): variance maps like the paper's Figs. 5-11, the
VO-only map beside the Gamma-SLAM map, the effective sample size over frames (Fig. 4, top) and
the position error against distance travelled.

Map inputs are expected-std arrays [Nx, Ny] (axis 0 is x, NaN = unknown), the world position of
cell (0, 0)'s corner and the cell side, as in ``gridmap.GridMap``. Colours: dark = flat,
bright = tall/rough, on a log scale; unobserved cells are drawn in a muted blue-grey. Every map
figure has a legend naming each line, its start (circle) and end (square), and that colour.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import LogNorm
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from matplotlib.ticker import MaxNLocator
from matplotlib.transforms import Affine2D

__all__ = [
    "MIN_ERROR_SPAN",
    "draw_line",
    "draw_map",
    "error_along_distance",
    "map_legend",
    "save_errors_png",
    "save_ess_png",
    "save_ground_truth_png",
    "save_map_comparison_png",
    "save_map_png",
    "save_maps_png",
]

_UNKNOWN = (0.16, 0.19, 0.24)
_LEGEND_FACE = (0.32, 0.32, 0.34)
_STD_RANGE = (0.01, 1.0)  # metres: sand .. walls
_STD_LABEL = "expected std of heights (m)\ndark = flat, bright = rough"
_PATH = {"color": "white", "lw": 0.8}
# errors.png's error axis spans at least this (metres): a still vehicle's sub-millimetre
# errors are drawn as the near-zero they are, not stretched over the whole axis
MIN_ERROR_SPAN = 0.05
_TRUTH = {"color": "cyan", "ls": "--", "lw": 1.0}


def draw_map(ax: plt.Axes, std: np.ndarray, origin: Sequence[float], resolution: float,
             path: np.ndarray | None = None, title: str | None = None,
             std_range: tuple[float, float] = _STD_RANGE, cmap: str = "inferno",
             path_label: str | None = None, marks: bool = True):
    """Draw one expected-std map (and a path [T, >=2] in white, labelled ``path_label`` for the
    legend, its start and end marked when ``marks``) on ``ax``; returns the image. ``origin``:
    cell (0, 0)'s corner (x, y), or (x, y, heading) for a lattice turned by ``heading``
    radians in the frame (``GridMap.heading``; a map of ``[map] axes = "start"``)."""
    std = np.asarray(std, dtype=np.float64)
    if std.ndim != 2:
        raise ValueError(f"std must be a 2-D [Nx, Ny] array, got shape {std.shape}")
    if not resolution > 0:
        raise ValueError(f"resolution must be positive, got {resolution}")
    x0, y0, heading = _placement(origin)
    extent = (x0, x0 + std.shape[0] * resolution, y0, y0 + std.shape[1] * resolution)
    colormap = matplotlib.colormaps[cmap].with_extremes(bad=_UNKNOWN)
    shown = np.ma.masked_invalid(np.clip(std, *std_range))
    turn = {"transform": Affine2D().rotate(heading) + ax.transData} if heading else {}
    im = ax.imshow(shown.T, origin="lower", extent=extent, cmap=colormap,
                   norm=LogNorm(*std_range), interpolation="nearest", **turn)
    if path is not None:
        draw_line(ax, path, path_label, marks=marks, alpha=0.9, **_PATH)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    if title:
        ax.set_title(title)
    return im


def draw_line(ax: plt.Axes, xy: np.ndarray, label: str | None = None, marks: bool = True,
              **style) -> None:
    """A path [T, >=2] on ``ax`` (NaN rows are gaps), a circle at its first known point and a
    square at its last when ``marks``."""
    xy = np.asarray(xy, np.float64)
    if xy.ndim != 2 or xy.shape[1] < 2:
        raise ValueError(f"a path must be [T, >=2], got shape {xy.shape}")
    ax.plot(xy[:, 0], xy[:, 1], label=label, **style)
    known = np.flatnonzero(np.isfinite(xy[:, :2]).all(axis=1))
    if marks and known.size:
        color = style.get("color", "white")
        for i, marker in ((known[0], "o"), (known[-1], "s")):
            ax.plot(xy[i, 0], xy[i, 1], marker, ms=6, mfc=color, mec="black", mew=0.8,
                    zorder=5)


def map_legend(ax: plt.Axes, std: np.ndarray | Sequence[np.ndarray] | None = None,
               marks: bool = True, loc: str = "best") -> None:
    """The legend of a map panel: its labelled lines, the start and end marks, and the
    unobserved colour (when ``std`` has unobserved cells, or ``std`` is None)."""
    handles, _ = ax.get_legend_handles_labels()
    if marks and handles:
        for marker, name in (("o", "start"), ("s", "end")):
            handles.append(Line2D([], [], ls="", marker=marker, ms=6, mfc="0.85", mec="black",
                                  label=name))
    maps = [] if std is None else [std] if isinstance(std, np.ndarray) else list(std)
    if std is None or any(not np.isfinite(np.asarray(s)).all() for s in maps):
        handles.append(Patch(facecolor=_UNKNOWN, edgecolor="0.8", lw=0.6, label="unobserved"))
    ax.legend(handles=handles, loc=loc, fontsize=8, facecolor=_LEGEND_FACE, framealpha=0.85,
              edgecolor="0.6", labelcolor="white")


def save_map_png(out: str | Path, std: np.ndarray, origin: Sequence[float], resolution: float,
                 path: np.ndarray | None = None, title: str | None = None, dpi: int = 120,
                 path_label: str = "path") -> Path:
    """One map, coloured by expected standard deviation, with the path drawn."""
    out = Path(out)
    std = np.asarray(std)
    w, h = _figsize(std.shape, 1)
    fig, ax = plt.subplots(figsize=(w, h), layout="compressed")
    im = draw_map(ax, std, origin, resolution, path, title or "Map by expected std of heights",
                  path_label=path_label)
    map_legend(ax, std)
    window = _data_window(std, origin, resolution)
    if window is not None:
        ax.set_xlim(window[0], window[1])
        ax.set_ylim(window[2], window[3])
    fig.colorbar(im, ax=ax, label=_STD_LABEL, shrink=0.8)
    fig.savefig(out, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return out


def save_map_comparison_png(out: str | Path, vo_std: np.ndarray, vo_origin: Sequence[float],
                            slam_std: np.ndarray, slam_origin: Sequence[float], resolution: float,
                            vo_path: np.ndarray | None = None,
                            slam_path: np.ndarray | None = None,
                            titles: tuple[str, str] = ("VO only", "Gamma-SLAM"),
                            suptitle: str | None = None, dpi: int = 120,
                            path_labels: tuple[str, str] = ("VO path", "Gamma-SLAM path")
                            ) -> Path:
    """The VO-only map beside the SLAM map (paper Figs. 5, 6, 8, 9, 11), same colour scale."""
    out = Path(out)
    shape = (max(vo_std.shape[0], slam_std.shape[0]), max(vo_std.shape[1], slam_std.shape[1]))
    w, h = _figsize(shape, 2)
    fig, axes = plt.subplots(1, 2, figsize=(w, h), layout="compressed")
    draw_map(axes[0], vo_std, vo_origin, resolution, vo_path, titles[0],
             path_label=path_labels[0])
    im = draw_map(axes[1], slam_std, slam_origin, resolution, slam_path, titles[1],
                  path_label=path_labels[1])
    for ax, std in zip(axes, (vo_std, slam_std)):
        map_legend(ax, std)
    # one common window around the known cells, so both panels show the same place and scale
    windows = [w for w in (_data_window(vo_std, vo_origin, resolution),
                           _data_window(slam_std, slam_origin, resolution)) if w is not None]
    if windows:
        box = np.array(windows)
        for ax in axes:
            ax.set_xlim(box[:, 0].min(), box[:, 1].max())
            ax.set_ylim(box[:, 2].min(), box[:, 3].max())
    fig.colorbar(im, ax=list(axes), label=_STD_LABEL, shrink=0.8)
    fig.suptitle(suptitle or "Map built at the VO poses beside the Gamma-SLAM map "
                 "(same colour scale)")
    fig.savefig(out, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return out


def save_ground_truth_png(out: str | Path, vo_std: np.ndarray, vo_origin: Sequence[float],
                          slam_std: np.ndarray, slam_origin: Sequence[float], resolution: float,
                          ground_truth: np.ndarray, vo_path: np.ndarray, slam_path: np.ndarray,
                          dpi: int = 120, suptitle: str | None = None) -> Path:
    """The VO-only and Gamma-SLAM maps with their paths (white) and the ground truth (cyan,
    dashed) over both, in the maps' frame (``metrics.ground_truth_in_map_frame``): where a
    path leaves the truth, the map built along it is displaced as much."""
    out = Path(out)
    gt = np.asarray(ground_truth, np.float64)
    if gt.ndim != 2 or gt.shape[1] < 2:
        raise ValueError(f"ground_truth must be [T, >=2], got shape {gt.shape}")
    shape = (max(vo_std.shape[0], slam_std.shape[0]), max(vo_std.shape[1], slam_std.shape[1]))
    w, h = _figsize(shape, 2)
    fig, axes = plt.subplots(1, 2, figsize=(w, h), layout="compressed")
    draw_map(axes[0], vo_std, vo_origin, resolution, vo_path, "VO only", path_label="VO path")
    im = draw_map(axes[1], slam_std, slam_origin, resolution, slam_path, "Gamma-SLAM",
                  path_label="Gamma-SLAM path")
    windows = [w for w in (_data_window(vo_std, vo_origin, resolution),
                           _data_window(slam_std, slam_origin, resolution)) if w is not None]
    for ax, std in zip(axes, (vo_std, slam_std)):
        draw_line(ax, gt, "ground truth", **_TRUTH)
        map_legend(ax, std)
        if windows:
            box = np.array(windows)
            ax.set_xlim(box[:, 0].min(), box[:, 1].max())
            ax.set_ylim(box[:, 2].min(), box[:, 3].max())
    fig.colorbar(im, ax=list(axes), label=_STD_LABEL, shrink=0.8)
    fig.suptitle(suptitle or "Ground truth over the maps and paths "
                 "(anchored at the first known pose; errors.png shows the error)")
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
    ax.plot(x, ess, lw=1.0, color="tab:blue", label="effective particles J_eff")
    if threshold is not None:
        ax.axhline(threshold * num_particles, color="grey", ls="--", lw=0.8,
                   label=f"resampling threshold ({threshold:g} J)")
    if resampled is not None and np.any(resampled):  # no legend entry for what did not happen
        r = np.asarray(resampled, dtype=bool)
        ax.plot(x[r], ess[r], "v", color="tab:red", ms=4, label=f"resampled ({r.sum()} times)")
    ax.set_ylim(0, num_particles * 1.05)
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))  # frames are whole numbers
    ax.set_xlabel("frame (index)")
    ax.set_ylabel("J_eff (particles)")
    ax.set_title(title or f"Effective number of particles (J = {num_particles})")
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=dpi)
    plt.close(fig)
    return out


def error_along_distance(ground_truth: np.ndarray, estimate: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """(distance [K], error [K]) over the K frames with a known ground-truth position: the
    distance travelled along the ground truth to each (m, gaps bridged by a straight line) and
    the estimate's position error there (m) after the rigid fit the RMS uses
    (``metrics.rigid_fit_2d`` over those frames, so the errors' RMS is the summary's RMS).
    Empty with fewer than 2 such frames."""
    from gslam_jax.metrics import apply_rigid, rigid_fit_2d
    from gslam_jax.run import known_positions

    gt = np.asarray(ground_truth, np.float64)
    est = np.asarray(estimate, np.float64)
    if gt.ndim != 2 or gt.shape[1] < 2:
        raise ValueError(f"ground_truth must be [T, >=2], got shape {gt.shape}")
    if est.ndim != 2 or est.shape[1] < 2 or len(est) != len(gt):
        raise ValueError(f"estimate must be [{len(gt)}, >=2] like ground_truth, "
                         f"got shape {est.shape}")
    frames = np.flatnonzero(known_positions(gt))
    if frames.size < 2:
        return np.zeros(0), np.zeros(0)
    ref, path = gt[frames, :2], est[frames, :2]
    moved = apply_rigid(path, rigid_fit_2d(path, ref))
    distance = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(ref, axis=0).T))])
    return distance, np.hypot(*(moved - ref).T)


def save_errors_png(out: str | Path, ground_truth: np.ndarray,
                    paths: Sequence[tuple[str, np.ndarray]], title: str | None = None,
                    dpi: int = 120) -> Path:
    """Position error (m) against distance travelled along the ground truth (m) for each
    (label, path [T, >=2]) (``error_along_distance``), the RMS in each label."""
    out = Path(out)
    fig, ax = plt.subplots(figsize=(8, 3.5))
    colors = ("tab:orange", "tab:blue", "tab:green", "tab:purple")
    for (label, path), color in zip(paths, colors * len(paths)):
        distance, error = error_along_distance(ground_truth, path)
        if distance.size:
            rms = float(np.sqrt(np.mean(error ** 2)))
            ax.plot(distance, error, lw=1.0, color=color, label=f"{label} (RMS {_metres(rms)})")
    ax.set_xlabel("distance travelled along the ground truth (m)")
    ax.set_ylabel("position error (m)")
    ax.set_ylim(0, max(ax.get_ylim()[1], MIN_ERROR_SPAN))
    ax.set_title(title or "Position error after the rigid fit of the RMS "
                 "(frames with ground truth)")
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=dpi)
    plt.close(fig)
    return out


def _metres(value: float) -> str:
    """A length for a label: millimetres under 1 cm (three figures), else metres."""
    return f"{value * 1e3:.3g} mm" if abs(value) < 0.01 else f"{value:.3f} m"


def _placement(origin: Sequence[float]) -> tuple[float, float, float]:
    """(x, y, heading) of a map's ``origin`` argument: (x, y) or (x, y, heading)."""
    if len(origin) not in (2, 3):
        raise ValueError(f"a map's origin must be (x, y) or (x, y, heading), got {origin}")
    return float(origin[0]), float(origin[1]), float(origin[2]) if len(origin) == 3 else 0.0


def _data_window(std: np.ndarray, origin: Sequence[float], resolution: float,
                 margin: float = 2.0) -> tuple[float, float, float, float] | None:
    """(x0, x1, y0, y1) around the known (finite) cells plus ``margin`` metres; None if none.
    A turned lattice (``draw_map``'s ``origin``): around its known box's turned corners."""
    known = np.isfinite(np.asarray(std))
    if not known.any():
        return None
    i = np.flatnonzero(known.any(axis=1))
    j = np.flatnonzero(known.any(axis=0))
    x0, y0, heading = _placement(origin)
    xs = np.array([x0 + i[0] * resolution, x0 + (i[-1] + 1) * resolution])
    ys = np.array([y0 + j[0] * resolution, y0 + (j[-1] + 1) * resolution])
    cx, cy = (a.ravel() for a in np.meshgrid(xs, ys))
    c, s = np.cos(heading), np.sin(heading)
    cx, cy = c * cx - s * cy, s * cx + c * cy
    return (cx.min() - margin, cx.max() + margin, cy.min() - margin, cy.max() + margin)


def _figsize(shape: tuple[int, ...], panels: int) -> tuple[float, float]:
    if len(shape) != 2:
        raise ValueError(f"std must be a 2-D [Nx, Ny] array, got shape {shape}")
    aspect = shape[1] / max(shape[0], 1)  # height / width of one panel
    width = 6.5 * panels
    return width + 1.5, float(np.clip(6.5 * aspect, 2.5, 10.0)) + 0.8


def save_maps_png(out: str | Path, panels: Sequence[tuple[str, np.ndarray, Sequence[float],
                                                           np.ndarray | None]],
                  resolution: float, suptitle: str | None = None, dpi: int = 120,
                  path_labels: Sequence[str] | None = None) -> Path:
    """Maps side by side in one frame and one window, same colour scale: panels of (title,
    expected std [Nx, Ny], origin, path [T, >=2] or None), e.g. run A, run B placed in A's
    frame, and their merge. ``path_labels`` name each panel's path in its legend (default
    "path of TITLE")."""
    out = Path(out)
    shape = (max(p[1].shape[0] for p in panels), max(p[1].shape[1] for p in panels))
    w, h = _figsize(shape, len(panels))
    fig, axes = plt.subplots(1, len(panels), figsize=(w, h), squeeze=False,
                             layout="compressed")
    axes = list(axes[0])
    labels = list(path_labels) if path_labels is not None else \
        [f"path of {p[0]}" for p in panels]
    if len(labels) != len(panels):
        raise ValueError(f"path_labels has {len(labels)} labels for {len(panels)} panels")
    im = None
    for ax, (title, std, origin, path), label in zip(axes, panels, labels):
        im = draw_map(ax, std, origin, resolution, path, title, path_label=label)
        map_legend(ax, std)
    windows = [w for w in (_data_window(p[1], p[2], resolution) for p in panels) if w]
    if windows:
        box = np.array(windows)
        for ax in axes:
            ax.set_xlim(box[:, 0].min(), box[:, 1].max())
            ax.set_ylim(box[:, 2].min(), box[:, 3].max())
    fig.colorbar(im, ax=axes, label=_STD_LABEL, shrink=0.8)
    fig.suptitle(suptitle or "Maps in one frame (same colour scale)")
    fig.savefig(out, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return out
