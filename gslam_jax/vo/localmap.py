"""Local-map observations (paper 6.3): stereo points -> robot-centred grids of height statistics.

Points arrive per frame in the gravity-aligned robot frame (x forward, y left, z up, metres,
origin on the ground under the robot). Several frames are fused, with their VO poses, into one
robot-centred local map every ``travel`` metres; the local map is the filter's observation z_t.
Each cell holds the sufficient statistics (n, sum z, sum z^2) of the point heights (eq. 5), in
float64; ``cells.obs_from_stats`` turns them into (k, S).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Iterable, Iterator, NamedTuple

import numpy as np

from gslam_jax.choices import AUTO_LOCALMAP_LATTICE, LOCALMAP_LATTICES

if TYPE_CHECKING:
    from gslam_jax.config import Config

__all__ = ["LocalMapParams", "localmap_params", "LocalMapBuilder", "LocalMaps", "points_to_stats",
           "relative_pose", "transform_points", "lattice_heading", "map_axes_heading",
           "build_local_maps"]


@dataclass(frozen=True)
class LocalMapParams:
    """How points become local maps.

    resolution: cell side, metres (paper 0.16 or 0.15).
    cells: side L of the square robot-centred grid; 0 picks the smallest multiple of 8 that
        holds ``max_range`` on every side.
    max_range: range gate, metres of horizontal distance from the sensor at capture (paper 5/10).
    min_height, max_height: height band kept, metres relative to the robot base; points above
        ``max_height`` are overhangs (canopy) and are removed.
    travel: metres of travel fused into one local map (paper: "a few metres").
    lattice: the local map's axes. "robot": the robot's at the local map's frame (the
        paper's). "map": the map's, at the VO pose of that frame: the points are binned on a
        lattice turned by minus the VO heading (``Run.lattice_headings``), so that a particle
        near the VO pose places its cells on the map's cells one for one. A lattice turned
        against the map's places cells by their centres, two into some map cells and none
        into others, and the result then depends on the map frame's orientation
        (docs/notebook/results.md, "The map frame's orientation").
    axes: the map's axes a "map" lattice lies on (``[map] axes``): the robot's at its start
        pose ("start"; ``map_axes_heading``), or the frame's ("frame").
    """

    resolution: float = 0.16
    cells: int = 0
    max_range: float = 10.0
    min_height: float = -2.0
    max_height: float = 2.0
    travel: float = 2.0
    lattice: str = "robot"
    axes: str = "start"

    @property
    def size(self) -> int:
        if self.cells > 0:
            return int(self.cells)
        need = int(np.ceil(2.0 * self.max_range / self.resolution))
        return int(8 * np.ceil(need / 8))


def localmap_params(config: Config, sensor: str | None = None) -> LocalMapParams:
    """How a config's [localmap] and [map] sections turn points into local maps made by
    ``sensor`` (``choices.SENSORS``; None: "points"), which resolves ``lattice = "auto"``
    (``choices.AUTO_LOCALMAP_LATTICE``)."""
    lm = config.localmap
    lattice = lm.lattice
    if lattice == "auto":
        if sensor is not None and sensor not in AUTO_LOCALMAP_LATTICE:
            from gslam_jax.config import ConfigError
            raise ConfigError(f"sensor must be one of {', '.join(AUTO_LOCALMAP_LATTICE)}, "
                              f"got {sensor!r}")
        lattice = AUTO_LOCALMAP_LATTICE[sensor or "points"]
    return LocalMapParams(resolution=config.map.resolution, cells=lm.cells,
                          max_range=lm.max_range, min_height=lm.min_height,
                          max_height=lm.max_height, travel=lm.travel, lattice=lattice,
                          axes=config.map.axes)


def map_axes_heading(axes: str, start_pose: np.ndarray | None) -> float:
    """The angle of the map's axes in the frame of a run that starts at ``start_pose`` (None:
    zeros), by ``[map] axes`` (``choices.MAP_AXES``): 0 for the frame's ("frame"), the start
    heading for the robot's ("start"). The filter's map lattice lies on them
    (``driver.map_axes.map_heading``), and a "map" local lattice is turned onto them
    (``LocalMapBuilder.axes_heading``)."""
    if axes == "start" and start_pose is not None:
        return float(np.asarray(start_pose, np.float64)[2])
    return 0.0


def relative_pose(ref: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Pose of ``pose`` expressed in the frame of ``ref`` (both world (x, y, theta))."""
    c, s = np.cos(ref[2]), np.sin(ref[2])
    dx, dy = pose[0] - ref[0], pose[1] - ref[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, pose[2] - ref[2]])


def lattice_heading(vo_heading: float, lattice: str) -> float:
    """The angle of a local map's lattice against the robot frame (``Run.lattice_headings``)
    for the VO heading of its frame: 0 ("robot"), or minus that heading wrapped into
    (-pi, pi] ("map": the lattice on the map's axes)."""
    if lattice == "robot":
        return 0.0
    if lattice != "map":
        raise ValueError(f"[localmap] lattice '{lattice}' unknown: one of "
                         f"{', '.join(LOCALMAP_LATTICES)} ('auto' resolved by the sensor "
                         "before, ``localmap_params``)")
    return float(-np.angle(np.exp(1j * vo_heading)))


def transform_points(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Move robot-frame points [N, 3] into the frame in which the robot stands at ``pose``."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    out = np.empty_like(points, dtype=np.float64)
    out[:, 0] = pose[0] + c * points[:, 0] - s * points[:, 1]
    out[:, 1] = pose[1] + s * points[:, 0] + c * points[:, 1]
    out[:, 2] = points[:, 2]
    return out


def points_to_stats(points: np.ndarray, params: LocalMapParams,
                    out: np.ndarray | None = None, heading: float = 0.0
                    ) -> tuple[np.ndarray, int]:
    """Bin points (already in the local-map frame) into [L, L, 3] (n, sum z, sum z^2), on a
    lattice turned by ``heading`` radians about the local map's centre (``lattice_heading``):
    a point p lands in the cell of R(-heading) p.

    Points outside the grid or outside the height band are dropped; returns the statistics and
    the number of points that fell outside the grid (height-band removals are intended and not
    counted). ``out`` accumulates in place when given.
    """
    L, res = params.size, params.resolution
    if out is None:
        out = np.zeros((L, L, 3), dtype=np.float64)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    points = points[np.isfinite(points).all(axis=1)]
    z = points[:, 2]
    points = points[(z >= params.min_height) & (z <= params.max_height)]
    if heading:
        c, s = np.cos(heading), np.sin(heading)
        x, y = points[:, 0], points[:, 1]
        points = np.stack([c * x + s * y, -s * x + c * y, points[:, 2]], axis=1)
    i = np.floor(points[:, 0] / res).astype(np.int64) + L // 2
    j = np.floor(points[:, 1] / res).astype(np.int64) + L // 2
    inside = (i >= 0) & (i < L) & (j >= 0) & (j < L)
    flat = i[inside] * L + j[inside]
    z = points[inside, 2]
    view = out.reshape(L * L, 3)
    view[:, 0] += np.bincount(flat, minlength=L * L)
    view[:, 1] += np.bincount(flat, weights=z, minlength=L * L)
    view[:, 2] += np.bincount(flat, weights=z * z, minlength=L * L)
    return out, int((~inside).sum())


def range_gate(points: np.ndarray, max_range: float) -> np.ndarray:
    """Keep robot-frame points within ``max_range`` metres horizontally of the sensor."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return points[np.hypot(points[:, 0], points[:, 1]) <= max_range]


@dataclass
class LocalMapBuilder:
    """Streams frames (VO pose, points) and emits a local map every ``params.travel`` metres.

    The emitted map is centred on the robot at the last frame fused into it; earlier frames'
    points are moved into that frame with the VO poses (paper 6.3: VO drift over a few metres is
    negligible). ``dropped_points`` counts points that fell outside the local grid.
    """

    params: LocalMapParams
    axes_heading: float = 0.0  # the map's axes in the VO poses' frame (``map_axes_heading``)
    dropped_points: int = 0
    lattice_headings: list[float] = field(default_factory=list)
    _frames: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    _travel: float = 0.0
    _last_pose: np.ndarray | None = None

    def add(self, vo_pose: np.ndarray, points: np.ndarray) -> np.ndarray | None:
        """Add one frame; return the [L, L, 3] local map when enough travel has accumulated."""
        vo_pose = np.asarray(vo_pose, dtype=np.float64)
        if self._last_pose is not None:
            self._travel += float(np.hypot(*(vo_pose[:2] - self._last_pose[:2])))
        self._last_pose = vo_pose
        self._frames.append((vo_pose, range_gate(points, self.params.max_range)))
        if self._travel >= self.params.travel:
            return self.flush()
        return None

    def flush(self) -> np.ndarray | None:
        """Emit whatever has been fused so far (None if nothing was added)."""
        if not self._frames:
            return None
        ref = self._frames[-1][0]
        heading = lattice_heading(float(ref[2]) - self.axes_heading, self.params.lattice)
        stats = np.zeros((self.params.size, self.params.size, 3))
        for pose, pts in self._frames:
            _, dropped = points_to_stats(transform_points(pts, relative_pose(ref, pose)),
                                         self.params, out=stats, heading=heading)
            self.dropped_points += dropped
        self.lattice_headings.append(heading)
        self._frames.clear()
        self._travel = 0.0
        return stats


class LocalMaps(NamedTuple):
    """A sequence's local maps (``build_local_maps``)."""

    obs_index: np.ndarray         # [T] int32, -1 where a frame completes none
    local_maps: np.ndarray        # [M, L, L, 3]
    dropped_points: int
    lattice_headings: np.ndarray  # [M] (``Run.lattice_headings``)


def build_local_maps(vo_poses: np.ndarray, frames: Iterable[np.ndarray],
                     params: LocalMapParams, start_pose: np.ndarray | None = None) -> LocalMaps:
    """Fuse a whole sequence: obs_index [T], local_maps [M, L, L, 3], the dropped points and
    the lattice headings [M] (a "map" lattice on the axes ``map_axes_heading`` gives for the
    Run's ``start_pose``).

    The first local map is emitted at frame 0 (the robot starts with an observation of where it
    stands), then every ``travel`` metres; a trailing partial segment is not emitted.
    """
    builder = LocalMapBuilder(params, axes_heading=map_axes_heading(params.axes, start_pose))
    obs_index, maps = [], []
    it: Iterator[np.ndarray] = iter(frames)
    poses = np.asarray(vo_poses)
    end = object()
    for t, pose in enumerate(poses):
        points = next(it, end)
        if points is end:
            raise ValueError(f"build_local_maps: {len(poses)} poses but only {t} point frames")
        stats = builder.add(pose, points)
        if t == 0 and stats is None:
            stats = builder.flush()
        if stats is not None:
            obs_index.append(len(maps))
            maps.append(stats)
        else:
            obs_index.append(-1)
    if next(it, end) is not end:
        raise ValueError(f"build_local_maps: more point frames than the {len(poses)} poses")
    L = params.size
    local_maps = np.stack(maps) if maps else np.zeros((0, L, L, 3))
    return LocalMaps(np.asarray(obs_index, dtype=np.int32), local_maps, builder.dropped_points,
                     np.asarray(builder.lattice_headings, np.float64))
