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
from typing import NamedTuple

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
    "save_utm_map_png",
]

_UNKNOWN = (0.16, 0.19, 0.24)
_LEGEND_FACE = (0.32, 0.32, 0.34)
_STD_RANGE = (0.01, 1.0)  # metres: sand .. walls
_STD_LABEL = "expected std of heights (m)\ndark = flat, bright = rough"
_PATH = {"color": "white", "lw": 0.8}
# errors.png's error axis spans at least this (metres): a still vehicle's sub-millimetre
# errors are drawn as the near-zero they are, not stretched over the whole axis
MIN_ERROR_SPAN = 0.05
_PATH = {**_PATH, "zorder": 3}
_TRUTH = {"color": "cyan", "ls": (0, (5, 3)), "lw": 2.0, "alpha": 0.85, "zorder": 2}
STRIP_ASPECT = 0.5     # map windows less tall than this times their width are strips
MIN_PANEL_INCHES = 2.0  # a strip's panel is at least this tall (the map then shows more
                        # around the path)


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
                    zorder=5, clip_on=False)


def map_legend(ax: plt.Axes, std: np.ndarray | Sequence[np.ndarray] | None = None,
               marks: bool = True, loc: str = "best",
               outside: tuple[float, float] | None = None) -> None:
    """The legend of a map panel: its labelled lines, the start and end marks, and the
    unobserved colour (when ``std`` has unobserved cells, or ``std`` is None). ``outside``:
    the legend's ``loc`` point at this place in axes fraction (e.g. (1.02, 1) with loc "upper
    left": right of the map), in one row when below the map."""
    handles, _ = ax.get_legend_handles_labels()
    if marks and handles:
        for marker, name in (("o", "start"), ("s", "end")):
            handles.append(Line2D([], [], ls="", marker=marker, ms=6, mfc="0.85", mec="black",
                                  label=name))
    maps = [] if std is None else [std] if isinstance(std, np.ndarray) else list(std)
    if std is None or any(not np.isfinite(np.asarray(s)).all() for s in maps):
        handles.append(Patch(facecolor=_UNKNOWN, edgecolor="0.8", lw=0.6, label="unobserved"))
    place = {} if outside is None else {"bbox_to_anchor": outside}
    below = outside is not None and outside[1] < 0
    ax.legend(handles=handles, loc=loc, fontsize=8, facecolor=_LEGEND_FACE, framealpha=0.85,
              edgecolor="0.6", labelcolor="white", ncol=len(handles) if below else 1, **place)


class _Panel(NamedTuple):
    """One map panel: its title, expected std [Nx, Ny], origin (``draw_map``) and lines, each
    (path [T, >=2], legend label, style for ``draw_line``), the first drawn as the map's path."""

    title: str | None
    std: np.ndarray
    origin: Sequence[float]
    lines: list[tuple[np.ndarray, str, dict]]


def _save_map_panels(out: str | Path, panels: Sequence[_Panel], resolution: float,
                     suptitle: str | None, dpi: int,
                     axis_labels: tuple[str, str] | None = None) -> Path:
    """Map panels in one window and one colour scale, laid out for the window's shape
    (``_arrange``): side by side, or stacked when the window is a wide strip (KITTI's roads);
    each panel's legend outside its map, so it never hides the path; the window around the
    observed cells and every line, so no start or end mark is clipped."""
    out = Path(out)
    window = _window(panels, resolution)
    rows, cols, figsize, strip = _arrange(window, len(panels))
    panel_inches = (figsize[1] - 1.6) / rows - 1.4  # a strip's panel height
    fig, axes = plt.subplots(rows, cols, figsize=figsize, squeeze=False, layout="constrained")
    axes = list(axes.ravel())
    im = None
    for ax, panel in zip(axes, panels):
        first, *rest = panel.lines or [(None, None, {})]
        im = draw_map(ax, panel.std, panel.origin, resolution, first[0], panel.title,
                      path_label=first[1])
        for xy, label, style in rest:
            draw_line(ax, xy, label, **style)
        if axis_labels:
            ax.set_xlabel(axis_labels[0])
            ax.set_ylabel(axis_labels[1])
        if strip:
            map_legend(ax, panel.std, loc="upper center", outside=(0.5, -0.45 / panel_inches))
        else:
            map_legend(ax, panel.std, loc="upper left", outside=(1.02, 1.0))
        if window is not None:
            ax.set_xlim(window[0], window[1])
            ax.set_ylim(*_strip_rows(window, panel_inches) if strip else window[2:])
    fig.colorbar(im, ax=axes, label=_STD_LABEL, shrink=0.8 if not strip else 0.6,
                 location="bottom" if strip else "right")
    if suptitle:
        fig.suptitle(suptitle)
    fig.savefig(out, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return out


def save_map_png(out: str | Path, std: np.ndarray, origin: Sequence[float], resolution: float,
                 path: np.ndarray | None = None, title: str | None = None, dpi: int = 120,
                 path_label: str = "path") -> Path:
    """One map, coloured by expected standard deviation, with the path drawn."""
    _check_std(std)
    lines = [] if path is None else [(path, path_label, _PATH)]
    return _save_map_panels(out, [_Panel(title or "Map by expected std of heights",
                                         np.asarray(std), origin, lines)], resolution, None, dpi)


def save_map_comparison_png(out: str | Path, vo_std: np.ndarray, vo_origin: Sequence[float],
                            slam_std: np.ndarray, slam_origin: Sequence[float], resolution: float,
                            vo_path: np.ndarray | None = None,
                            slam_path: np.ndarray | None = None,
                            titles: tuple[str, str] = ("VO only", "Gamma-SLAM"),
                            suptitle: str | None = None, dpi: int = 120,
                            path_labels: tuple[str, str] = ("VO path", "Gamma-SLAM path")
                            ) -> Path:
    """The VO-only map beside the SLAM map (paper Figs. 5, 6, 8, 9, 11), same colour scale."""
    panels = [_Panel(title, np.asarray(std), origin, [] if path is None else
                     [(path, label, _PATH)])
              for title, std, origin, path, label in zip(titles, (vo_std, slam_std),
                                                          (vo_origin, slam_origin),
                                                          (vo_path, slam_path), path_labels)]
    return _save_map_panels(out, panels, resolution, suptitle or "Map built at the VO poses "
                            "beside the Gamma-SLAM map (same colour scale)", dpi)


def save_ground_truth_png(out: str | Path, vo_std: np.ndarray, vo_origin: Sequence[float],
                          slam_std: np.ndarray, slam_origin: Sequence[float], resolution: float,
                          ground_truth: np.ndarray, vo_path: np.ndarray, slam_path: np.ndarray,
                          dpi: int = 120, suptitle: str | None = None) -> Path:
    """The VO-only and Gamma-SLAM maps with their paths (thin white, on top) and the ground
    truth (wide dashed cyan, underneath, so that both show where they overlap) over both, in
    the maps' frame (``metrics.ground_truth_in_map_frame``): where a path leaves the truth,
    the map built along it is displaced as much."""
    gt = np.asarray(ground_truth, np.float64)
    if gt.ndim != 2 or gt.shape[1] < 2:
        raise ValueError(f"ground_truth must be [T, >=2], got shape {gt.shape}")
    panels = [_Panel(title, np.asarray(std), origin,
                     [(path, label, _PATH), (gt, "ground truth", {**_TRUTH, "marks": False})])
              for title, std, origin, path, label in (
                  ("VO only", vo_std, vo_origin, vo_path, "VO path"),
                  ("Gamma-SLAM", slam_std, slam_origin, slam_path, "Gamma-SLAM path"))]
    return _save_map_panels(out, panels, resolution, suptitle or "Ground truth over the maps "
                            "and paths (anchored at the first known pose; errors.png shows the "
                            "error)", dpi)


def save_utm_map_png(out: str | Path, std: np.ndarray, transform: Sequence[float],
                     path: np.ndarray | None = None, crs: str = "UTM",
                     dpi: int = 120) -> Path:
    """The georeferenced map as a figure: a north-up expected-std raster ``std`` [rows, cols]
    (row 0 north, NaN = no data) placed by the GDAL affine ``transform`` (a, 0, c, 0, e, f)
    (``geotiff.north_up``), on easting and northing axes counted from a round 100 m corner
    that the axis labels name, with the path [T, >=2] in UTM, a legend and a colour bar."""
    std = np.asarray(std, np.float64)
    if std.ndim != 2:
        raise ValueError(f"std must be a 2-D [rows, cols] raster, got shape {std.shape}")
    a, b, c, d, e, f = (float(v) for v in transform)
    if b or d or not (a > 0 and e < 0):
        raise ValueError(f"a north-up transform (a, 0, c, 0, e, f) with a > 0 > e is needed, "
                         f"got {tuple(transform)}")
    east0, north0 = 100.0 * np.floor(c / 100.0), 100.0 * np.floor((f + e * std.shape[0]) / 100.0)
    lines = []
    if path is not None:
        xy = np.asarray(path, np.float64)[:, :2] - [east0, north0]
        lines = [(xy, "Gamma-SLAM path", _PATH)]
    # as a lattice of cells from its south-west corner: rows flipped, axes (easting, northing)
    grid = np.flipud(std).T
    return _save_map_panels(out, [_Panel(f"Gamma-SLAM map in {crs} (north up)", grid,
                                         (c - east0, f + e * std.shape[0] - north0), lines)],
                            a, None, dpi, (f"easting - {east0:,.0f} (m)",
                                           f"northing - {north0:,.0f} (m)"))


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
    from gslam_jax.evaluation.metrics import apply_rigid, rigid_fit_2d
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


def _check_std(std) -> None:
    if np.ndim(std) != 2:
        raise ValueError(f"std must be a 2-D [Nx, Ny] array, got shape {np.shape(std)}")


def _window(panels: Sequence[_Panel], resolution: float,
            margin: float = 2.0) -> tuple[float, float, float, float] | None:
    """(x0, x1, y0, y1) around every panel's known cells and every point of its lines, plus
    ``margin`` metres (``_data_window``); None with neither."""
    boxes = [w for w in (_data_window(p.std, p.origin, resolution, margin) for p in panels)
             if w is not None]
    for panel in panels:
        for xy, _, _ in panel.lines:
            xy = np.asarray(xy, np.float64)[:, :2]
            xy = xy[np.isfinite(xy).all(axis=1)]
            if len(xy):
                lo, hi = xy.min(axis=0) - margin, xy.max(axis=0) + margin
                boxes.append((lo[0], hi[0], lo[1], hi[1]))
    if not boxes:
        return None
    b = np.array(boxes)
    return b[:, 0].min(), b[:, 1].max(), b[:, 2].min(), b[:, 3].max()


def _strip_rows(window: tuple[float, float, float, float],
                panel_inches: float) -> tuple[float, float]:
    """A strip's y range: as tall as its panel (``panel_inches`` high, about 9.3 inches of map
    wide) shows at one scale with x, centred on the window, so a thin map gets a readable
    panel and shows more around itself."""
    half = 0.5 * max((window[1] - window[0]) * panel_inches / 9.3, window[3] - window[2])
    middle = 0.5 * (window[2] + window[3])
    return middle - half, middle + half


def _arrange(window: tuple[float, float, float, float] | None,
             panels: int) -> tuple[int, int, tuple[float, float], bool]:
    """(rows, columns, figure size in inches, strip) for map panels over ``window``: a window
    under ``STRIP_ASPECT`` as tall as wide is a strip, its panels stacked, each at least
    ``MIN_PANEL_INCHES`` tall with the legend below it; otherwise side by side, each panel
    6.5 inches wide and as tall as the window's shape asks (2.5 to 10 inches), the legend
    to its right."""
    aspect = 1.0 if window is None else \
        (window[3] - window[2]) / max(window[1] - window[0], 1e-9)
    if aspect < STRIP_ASPECT:
        height = max(10.0 * aspect, MIN_PANEL_INCHES)
        return panels, 1, (10.5, panels * (height + 1.4) + 1.6), True
    height = float(np.clip(6.5 * aspect, 2.5, 10.0))
    return 1, panels, (7.5 * panels + 1.5, height + 0.8), False


def save_maps_png(out: str | Path, panels: Sequence[tuple[str, np.ndarray, Sequence[float],
                                                           np.ndarray | None]],
                  resolution: float, suptitle: str | None = None, dpi: int = 120,
                  path_labels: Sequence[str] | None = None) -> Path:
    """Maps side by side in one frame and one window, same colour scale: panels of (title,
    expected std [Nx, Ny], origin, path [T, >=2] or None), e.g. run A, run B placed in A's
    frame, and their merge. ``path_labels`` name each panel's path in its legend (default
    "path of TITLE")."""
    labels = list(path_labels) if path_labels is not None else \
        [f"path of {p[0]}" for p in panels]
    if len(labels) != len(panels):
        raise ValueError(f"path_labels has {len(labels)} labels for {len(panels)} panels")
    return _save_map_panels(out, [_Panel(title, np.asarray(std), origin, [] if path is None
                                         else [(path, label, _PATH)])
                                  for (title, std, origin, path), label in zip(panels, labels)],
                            resolution, suptitle or "Maps in one frame (same colour scale)", dpi)
