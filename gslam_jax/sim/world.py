"""A simulated world: 2.5-D rasters that a ray caster can answer "what surface is here" from.

The world is a fine grid (default 0.05 m, well below the 0.16 m map cells) of

- ``ground``: bare-earth height (m),
- ``height``: top of whatever stands on the ground there (ground itself where nothing does),
- ``rough``: per-point height spread (m) of returns from that pixel (sand ~mm, grass/scrub dm),
- ``canopy_lo`` / ``canopy_hi``: an overhanging layer (tree crowns), ``canopy_lo = inf`` where none,
- ``material``: a ``Material`` code per pixel (the sensor uses it for texture-dependent dropouts).

Pixel (i, j) covers world x in [x0 + i res, x0 + (i+1) res), y likewise with j (axis 0 is x).
The stamping helpers below are the only way objects enter a world, so every generator
draws the same kinds of shapes.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

__all__ = ["Material", "World", "empty_world", "smooth_noise", "stamp_disk", "stamp_dome",
           "stamp_box", "stamp_clump", "stamp_canopy", "path_clearance_mask"]


class Material(IntEnum):
    """Surface classes; the sensor's dropout model keys on them."""

    SAND = 0
    GRASS = 1
    ROCK = 2
    POLE = 3
    BIN = 4
    BUILDING = 5
    BUSH = 6
    TREE = 7
    SCRUB = 8


@dataclass
class World:
    """Raster world (see module docstring). Arrays are float32 [W_x, W_y] except ``material``."""

    kind: str
    seed: int
    resolution: float
    origin: tuple[float, float]
    ground: np.ndarray
    height: np.ndarray
    rough: np.ndarray
    canopy_lo: np.ndarray
    canopy_hi: np.ndarray
    material: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.ground.shape)  # type: ignore[return-value]

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) in metres."""
        x0, y0 = self.origin
        return (x0, x0 + self.shape[0] * self.resolution, y0, y0 + self.shape[1] * self.resolution)

    @property
    def has_canopy(self) -> bool:
        return bool(np.isfinite(self.canopy_lo).any())

    def cell_of(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel indices (clipped to the raster) of world points ``xy`` [..., 2]."""
        xy = np.asarray(xy, dtype=np.float64)
        i = np.floor((xy[..., 0] - self.origin[0]) / self.resolution).astype(np.int64)
        j = np.floor((xy[..., 1] - self.origin[1]) / self.resolution).astype(np.int64)
        return np.clip(i, 0, self.shape[0] - 1), np.clip(j, 0, self.shape[1] - 1)

    def local(self, x: float, y: float, reach: float) -> "World":
        """A dense raster holding every pixel within ``reach`` metres of (x, y), for the
        sensor: the world itself (a tiled world gives a window of its tiles)."""
        return self

    def ground_at(self, xy: np.ndarray) -> np.ndarray:
        i, j = self.cell_of(xy)
        return self.ground[i, j].astype(np.float64)

    def obstacle_height(self) -> np.ndarray:
        """Height of objects above the bare ground (m), [W_x, W_y]."""
        return self.height - self.ground

    def fingerprint(self) -> str:
        """A short hash of the rasters, for reproducibility checks and logs."""
        import hashlib

        h = hashlib.sha256()
        for a in (self.ground, self.height, self.rough, self.canopy_lo, self.canopy_hi,
                  self.material):
            h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()[:16]


def empty_world(kind: str, seed: int, bounds: tuple[float, float, float, float],
                resolution: float = 0.05, ground: np.ndarray | None = None,
                base_rough: float = 0.005, material: Material = Material.SAND) -> World:
    """A flat (or given-ground) world covering ``bounds`` = (x_min, x_max, y_min, y_max)."""
    if not resolution > 0:
        raise ValueError(f"resolution must be positive, got {resolution}")
    x_min, x_max, y_min, y_max = bounds
    nx = int(np.ceil((x_max - x_min) / resolution))
    ny = int(np.ceil((y_max - y_min) / resolution))
    if nx <= 0 or ny <= 0:
        raise ValueError(f"bounds {bounds} give an empty raster")
    g = np.zeros((nx, ny), np.float32) if ground is None else ground.astype(np.float32)
    if g.shape != (nx, ny):
        raise ValueError(f"ground has shape {g.shape}, bounds need {(nx, ny)}")
    return World(kind=kind, seed=seed, resolution=resolution, origin=(x_min, y_min),
                 ground=g, height=g.copy(), rough=np.full((nx, ny), base_rough, np.float32),
                 canopy_lo=np.full((nx, ny), np.inf, np.float32),
                 canopy_hi=np.full((nx, ny), -np.inf, np.float32),
                 material=np.full((nx, ny), int(material), np.uint8))


def smooth_noise(shape: tuple[int, int], cell_px: float, rng: np.random.Generator) -> np.ndarray:
    """Value noise in [0, 1]: uniform randoms on a coarse lattice, bilinearly interpolated."""
    nx, ny = shape
    cx, cy = int(np.ceil(nx / cell_px)) + 2, int(np.ceil(ny / cell_px)) + 2
    coarse = rng.random((cx, cy))
    xi = np.arange(nx) / cell_px
    yi = np.arange(ny) / cell_px
    rows = np.stack([np.interp(yi, np.arange(cy), coarse[r]) for r in range(cx)])
    out = np.stack([np.interp(xi, np.arange(cx), rows[:, c]) for c in range(ny)], axis=1)
    # bilinear value noise has a smaller spread than its lattice: restretch to [0, 1]
    lo, hi = out.min(), out.max()
    return ((out - lo) / max(hi - lo, 1e-9)).astype(np.float32)


def _window(world: World, cx: float, cy: float, radius: float):
    """Index window and pixel-centre offsets (dx, dy) around (cx, cy); None if off-raster."""
    res = world.resolution
    i0 = int(np.floor((cx - radius - world.origin[0]) / res))
    i1 = int(np.ceil((cx + radius - world.origin[0]) / res)) + 1
    j0 = int(np.floor((cy - radius - world.origin[1]) / res))
    j1 = int(np.ceil((cy + radius - world.origin[1]) / res)) + 1
    i0, j0 = max(i0, 0), max(j0, 0)
    i1, j1 = min(i1, world.shape[0]), min(j1, world.shape[1])
    if i0 >= i1 or j0 >= j1:
        return None
    xs = world.origin[0] + (np.arange(i0, i1) + 0.5) * res - cx
    ys = world.origin[1] + (np.arange(j0, j1) + 0.5) * res - cy
    return (slice(i0, i1), slice(j0, j1)), xs[:, None], ys[None, :]


def _apply(world: World, win, mask: np.ndarray, top_above_ground: np.ndarray,
           rough: float, material: Material) -> None:
    sl = win
    base = world.ground[sl]
    new_top = base + top_above_ground
    take = mask & (new_top > world.height[sl])
    world.height[sl] = np.where(take, new_top, world.height[sl])
    world.rough[sl] = np.where(take, rough, world.rough[sl])
    world.material[sl] = np.where(take, int(material), world.material[sl])


def stamp_disk(world: World, cx: float, cy: float, radius: float, height: float,
               rough: float, material: Material) -> None:
    """A vertical cylinder (pole, trunk) of ``height`` above the ground."""
    w = _window(world, cx, cy, radius)
    if w is None:
        return
    sl, dx, dy = w
    mask = dx * dx + dy * dy <= radius * radius
    _apply(world, sl, mask, np.full(mask.shape, height, np.float32), rough, material)


def stamp_dome(world: World, cx: float, cy: float, rx: float, ry: float, angle: float,
               height: float, rough: float, material: Material) -> None:
    """An elliptic dome (rock): height * sqrt(1 - r^2) over a rotated ellipse."""
    w = _window(world, cx, cy, max(rx, ry))
    if w is None:
        return
    sl, dx, dy = w
    c, s = np.cos(angle), np.sin(angle)
    u, v = (c * dx + s * dy) / rx, (-s * dx + c * dy) / ry
    r2 = u * u + v * v
    mask = r2 <= 1.0
    _apply(world, sl, mask, (height * np.sqrt(np.clip(1.0 - r2, 0.0, 1.0))).astype(np.float32),
           rough, material)


def stamp_box(world: World, cx: float, cy: float, lx: float, ly: float, angle: float,
              height: float, rough: float, material: Material) -> None:
    """A rotated rectangular block (bin, building) with a flat top."""
    w = _window(world, cx, cy, 0.5 * np.hypot(lx, ly))
    if w is None:
        return
    sl, dx, dy = w
    c, s = np.cos(angle), np.sin(angle)
    u, v = c * dx + s * dy, -s * dx + c * dy
    mask = (np.abs(u) <= 0.5 * lx) & (np.abs(v) <= 0.5 * ly)
    _apply(world, sl, mask, np.full(mask.shape, height, np.float32), rough, material)


def stamp_clump(world: World, cx: float, cy: float, radius: float, height: float,
                density: float, rough: float, material: Material,
                rng: np.random.Generator) -> None:
    """Vegetation: a rounded clump whose pixels are present with probability ``density``.

    Spindly bushes (low density) let rays through to whatever is behind, dense ones do not;
    per-pixel heights vary, so a map cell over a bush sees a wide spread of heights.
    """
    w = _window(world, cx, cy, radius)
    if w is None:
        return
    sl, dx, dy = w
    r2 = (dx * dx + dy * dy) / (radius * radius)
    present = (r2 <= 1.0) & (rng.random(r2.shape) < density)
    top = height * np.sqrt(np.clip(1.0 - r2, 0.0, 1.0)) * rng.uniform(0.55, 1.0, r2.shape)
    _apply(world, sl, present, top.astype(np.float32), rough, material)


def stamp_canopy(world: World, cx: float, cy: float, radius: float, lo: float, hi: float,
                 density: float, rng: np.random.Generator) -> None:
    """A tree crown: an overhanging layer from ``lo`` to ``hi`` metres above the ground."""
    w = _window(world, cx, cy, radius)
    if w is None:
        return
    sl, dx, dy = w
    r2 = (dx * dx + dy * dy) / (radius * radius)
    present = (r2 <= 1.0) & (rng.random(r2.shape) < density)
    g = world.ground[sl]
    world.canopy_lo[sl] = np.where(present, np.minimum(world.canopy_lo[sl], g + lo),
                                   world.canopy_lo[sl])
    world.canopy_hi[sl] = np.where(present, np.maximum(world.canopy_hi[sl], g + hi),
                                   world.canopy_hi[sl])


def path_clearance_mask(world: World, path_xy: np.ndarray, radius: float,
                        spacing: float = 0.1) -> np.ndarray:
    """Boolean raster: pixels within ``radius`` metres of the polyline ``path_xy`` [N, 2]."""
    path_xy = np.asarray(path_xy, dtype=np.float64)
    seg = np.hypot(*np.diff(path_xy, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    ss = np.arange(0.0, s[-1] + spacing, spacing)
    pts = np.stack([np.interp(ss, s, path_xy[:, 0]), np.interp(ss, s, path_xy[:, 1])], axis=1)
    res = world.resolution
    i, j = world.cell_of(pts)
    centres = np.unique(i * world.shape[1] + j)
    ci, cj = centres // world.shape[1], centres % world.shape[1]
    r_px = int(np.ceil(radius / res))
    oi, oj = np.mgrid[-r_px:r_px + 1, -r_px:r_px + 1]
    keep = (oi * oi + oj * oj) * res * res <= radius * radius
    oi, oj = oi[keep], oj[keep]
    mask = np.zeros(world.shape, bool)
    for a in range(0, ci.size, 2048):  # chunks keep the temporary index arrays small
        ii = np.clip(ci[a:a + 2048, None] + oi[None, :], 0, world.shape[0] - 1)
        jj = np.clip(cj[a:a + 2048, None] + oj[None, :], 0, world.shape[1] - 1)
        mask[ii.ravel(), jj.ravel()] = True
    return mask
