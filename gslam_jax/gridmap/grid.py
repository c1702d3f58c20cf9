"""A finished variance grid map as a value: its cell statistics and where they lie.

A map is the (k, S) statistics of eq. 14 on a regular grid: cell (i, j) covers
x in [origin_x + i r, origin_x + (i + 1) r) and y likewise with j (axis 0 along x, axis 1
along y, as in ``gslam run``'s ``map.npz``), in the lattice's own axes. Those are the map
frame's turned by ``heading`` (the robot's start heading under ``[map] axes = "start"``, the
default; 0 on the frame's axes): a point p of the lattice's axes is R(heading) p in the map's
frame.
Because eq. 14 is a sum, two maps of the same
terrain combine by adding their statistics cell by cell once they share a frame and a lattice:
``transform`` carries a map into another frame and ``add`` sums maps on a common lattice.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import NamedTuple

import numpy as np

from gslam_jax.errors import InputError

__all__ = ["GridMap", "MapFileError", "load_map", "save_map", "known_cells", "transform",
           "add", "place", "compose", "invert_pose", "apply_pose", "turn_poses", "arc_length"]


class MapFileError(InputError):
    """A map file (``map.npz`` or a run folder) is missing or unusable; the message names the
    file and field."""


class GridMap(NamedTuple):
    """Variance grid map: k, S [H, W] float64 (k = 0: unknown cell), the x, y of cell
    (0, 0)'s corner in the lattice's axes, the cell side in metres, and the angle of the
    lattice's axes in the map's frame (radians; see the module)."""

    k: np.ndarray
    S: np.ndarray
    origin: tuple[float, float]
    resolution: float
    heading: float = 0.0

    @property
    def shape(self) -> tuple[int, int]:
        return self.k.shape  # type: ignore[return-value]

    @property
    def known(self) -> np.ndarray:
        return self.k > 0

    def expected_std(self) -> np.ndarray:
        """Posterior expected std of each cell's heights (``cells.expected_std``; NaN where
        unknown), float64."""
        from gslam_jax.rbpf import cells

        return np.asarray(cells.expected_std(self.k, self.S), dtype=np.float64)


def load_map(path: str | Path) -> GridMap:
    """The map of a ``gslam run`` results folder (its ``map.npz``) or of a ``.npz`` file with
    fields k, S, origin and resolution; a MapFileError names the file and field at fault."""
    path = Path(path)
    file = path / "map.npz" if path.is_dir() else path
    if not file.is_file():
        where = f"{path} has no map.npz" if path.is_dir() else f"{path} does not exist"
        raise MapFileError(f"{where}: give a gslam run results folder or its map.npz")
    try:
        data = np.load(file, allow_pickle=False)
        fields = {name: np.asarray(data[name]) for name in data.files}
    except Exception as err:  # zip, pickle or format errors: all mean an unreadable file
        raise MapFileError(f"{file}: not a readable .npz archive ({err})") from err
    missing = [f for f in ("k", "S", "origin", "resolution") if f not in fields]
    if missing:
        raise MapFileError(f"{file}: missing field(s) {', '.join(missing)} "
                           "(a map.npz holds k, S, origin and resolution)")
    k, S = fields["k"].astype(np.float64), fields["S"].astype(np.float64)
    origin, resolution = fields["origin"].astype(np.float64), fields["resolution"]
    if k.ndim != 2 or k.shape != S.shape or min(k.shape) < 1:
        raise MapFileError(f"{file}: k and S must be 2-D arrays of one shape, got "
                           f"{k.shape} and {S.shape}")
    if origin.shape != (2,) or not np.isfinite(origin).all():
        raise MapFileError(f"{file}: origin must be two finite numbers, got {origin.tolist()}")
    if resolution.size != 1 or not (np.isfinite(resolution) and float(resolution) > 0):
        raise MapFileError(f"{file}: resolution must be a positive number, got {resolution}")
    heading = fields.get("heading", np.float64(0.0))  # older files: the frame's axes
    if heading.size != 1 or not np.isfinite(heading):
        raise MapFileError(f"{file}: heading must be a finite number (radians), got {heading}")
    bad = ~np.isfinite(k) | ~np.isfinite(S) | (k < 0) | (S < 0) | ((k > 0) & (S <= 0))
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise MapFileError(f"{file}: {int(bad.sum())} cells have invalid statistics (k, S must "
                           f"be finite, k >= 0, S > 0 where k > 0), first at cell ({i}, {j}): "
                           f"k = {k[i, j]}, S = {S[i, j]}")
    return GridMap(k, np.where(k > 0, S, 0.0), (float(origin[0]), float(origin[1])),
                   float(resolution), float(heading))


def save_map(path: str | Path, grid: GridMap) -> None:
    """``grid`` as a ``map.npz`` (the format ``gslam run`` writes and ``load_map`` reads)."""
    from gslam_jax.io import save_map as save

    save(path, grid.k, grid.S, grid.origin, grid.resolution, heading=grid.heading)


def known_cells(grid: GridMap) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centres [N, 2] in the map's frame, metres; k [N], S [N]) of the known cells, in
    row-major order."""
    i, j = np.nonzero(grid.known)
    r = grid.resolution
    centres = np.column_stack([grid.origin[0] + (i + 0.5) * r, grid.origin[1] + (j + 0.5) * r])
    if grid.heading:
        centres = apply_pose(np.array([0.0, 0.0, grid.heading]), centres)
    return centres, grid.k[i, j], grid.S[i, j]


def apply_pose(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points [N, 2] of a frame placed by ``pose`` = (x, y, theta) into the outer frame."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    p = np.asarray(points, np.float64)
    return np.column_stack([pose[0] + c * p[:, 0] - s * p[:, 1],
                            pose[1] + s * p[:, 0] + c * p[:, 1]])


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """SE(2) composition a (+) b: the pose b of frame a, expressed in a's outer frame."""
    x, y = apply_pose(a, np.asarray(b[:2], np.float64)[None])[0]
    return np.array([x, y, math.remainder(a[2] + b[2], 2 * math.pi)])


def invert_pose(a: np.ndarray) -> np.ndarray:
    """The inverse SE(2) pose: compose(a, invert_pose(a)) = 0."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([-(c * a[0] + s * a[1]), s * a[0] - c * a[1], -a[2]])


def turn_poses(poses: np.ndarray, heading: float) -> np.ndarray:
    """Poses [..., 3] of a frame expressed in that frame turned by ``heading`` about its
    origin: each pose (0, 0, heading) (+) pose (``compose``), headings wrapped to (-pi, pi].
    A heading of 0 gives the poses as they are (unwrapped, their dtype kept), so that a run on
    the frame's own axes is the same to the bit whichever way it is carried."""
    if not heading:
        return np.asarray(poses)
    poses = np.asarray(poses, np.float64)
    c, s = math.cos(heading), math.sin(heading)
    x, y = poses[..., 0], poses[..., 1]
    return np.stack([c * x - s * y, s * x + c * y,
                     np.angle(np.exp(1j * (poses[..., 2] + heading)))], axis=-1)


def arc_length(poses: np.ndarray) -> np.ndarray:
    """[N] distance travelled from the first pose to each pose (m)."""
    xy = np.asarray(poses, np.float64)[:, :2]
    return np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])


def _lattice_index(grid: GridMap, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cell (i, j) of ``grid``'s lattice under each point of the map's frame (may lie outside
    its extent)."""
    r = grid.resolution
    if grid.heading:
        points = apply_pose(np.array([0.0, 0.0, -grid.heading]), points)
    return (np.floor((points[:, 0] - grid.origin[0]) / r).astype(np.int64),
            np.floor((points[:, 1] - grid.origin[1]) / r).astype(np.int64))


def transform(grid: GridMap, pose: np.ndarray, like: GridMap | None = None) -> GridMap:
    """``grid`` carried into an outer frame by ``pose`` (its frame's pose there): each known
    cell's centre is placed by the pose and its (k, S) added to the cell of the target lattice
    it falls in (the lattice of ``like``, else ``grid``'s own resolution with origin 0 on the
    outer frame's axes), so no statistic is lost or counted twice. The result spans exactly the
    cells that received one."""
    centres, k, S = known_cells(grid)
    res = grid.resolution if like is None else like.resolution
    base = GridMap(np.zeros((1, 1)), np.zeros((1, 1)), (0.0, 0.0) if like is None
                   else like.origin, res, 0.0 if like is None else like.heading)
    if not k.size:
        return base
    i, j = _lattice_index(base, apply_pose(np.asarray(pose, np.float64), centres))
    i0, j0 = i.min(), j.min()
    shape = (int(i.max() - i0 + 1), int(j.max() - j0 + 1))
    kk, SS = np.zeros(shape), np.zeros(shape)
    np.add.at(kk, (i - i0, j - j0), k)
    np.add.at(SS, (i - i0, j - j0), S)
    origin = (base.origin[0] + i0 * res, base.origin[1] + j0 * res)
    return GridMap(kk, SS, origin, res, base.heading)


def _offset(grid: GridMap, origin: tuple[float, float], resolution: float,
            heading: float = 0.0) -> tuple[int, int]:
    """Whole-cell offset of ``grid``'s origin from ``origin`` on a common lattice (axes at
    ``heading``)."""
    if abs(math.remainder(grid.heading - heading, 2 * math.pi)) > 1e-9:
        raise ValueError(f"maps whose lattices lie at {math.degrees(grid.heading):.4g} and "
                         f"{math.degrees(heading):.4g} deg do not share a lattice; transform "
                         "one onto the other first")
    if not math.isclose(grid.resolution, resolution, rel_tol=1e-9):
        raise ValueError(f"maps of resolution {grid.resolution} m and {resolution} m do not "
                         "share a lattice; transform one onto the other first")
    steps = [(grid.origin[a] - origin[a]) / resolution for a in (0, 1)]
    whole = [round(s) for s in steps]
    if any(abs(s - w) > 1e-6 for s, w in zip(steps, whole)):
        raise ValueError(f"map origins {grid.origin} and {origin} are not a whole number of "
                         f"{resolution} m cells apart; transform one onto the other first")
    return whole[0], whole[1]


def place(grid: GridMap, origin: tuple[float, float], shape: tuple[int, int]) -> GridMap:
    """``grid`` on the same lattice cut or padded to ``shape`` cells from ``origin`` (a whole
    number of cells away, in the lattice's axes). Raises ValueError when a known cell would
    fall outside."""
    di, dj = _offset(grid, origin, grid.resolution, grid.heading)
    H, W = shape
    kk, SS = np.zeros(shape), np.zeros(shape)
    i, j = np.nonzero(grid.known)
    ti, tj = i + di, j + dj
    inside = (ti >= 0) & (ti < H) & (tj >= 0) & (tj < W)
    if not inside.all():
        raise ValueError(f"{int((~inside).sum())} known cells of the map fall outside the "
                         f"{H} x {W} grid at origin {origin}")
    kk[ti, tj] = grid.k[i, j]
    SS[ti, tj] = grid.S[i, j]
    return GridMap(kk, SS, (float(origin[0]), float(origin[1])), grid.resolution,
                   grid.heading)


def add(*grids: GridMap) -> GridMap:
    """Eq. 14 over whole maps: the cell-by-cell sum of maps on one lattice, over the union of
    their extents."""
    res = grids[0].resolution
    first = grids[0].origin
    offsets = [_offset(g, first, res, grids[0].heading) for g in grids]
    lo = [min(o[a] for o in offsets) for a in (0, 1)]
    hi = [max(o[a] + g.shape[a] for o, g in zip(offsets, grids)) for a in (0, 1)]
    shape = (hi[0] - lo[0], hi[1] - lo[1])
    kk, SS = np.zeros(shape), np.zeros(shape)
    for (di, dj), g in zip(offsets, grids):
        i0, j0 = di - lo[0], dj - lo[1]
        sl = (slice(i0, i0 + g.shape[0]), slice(j0, j0 + g.shape[1]))
        kk[sl] += g.k
        SS[sl] += g.S
    return GridMap(kk, SS, (first[0] + lo[0] * res, first[1] + lo[1] * res), res,
                   grids[0].heading)
