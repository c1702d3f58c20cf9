"""Worlds in a corridor: terrain generated only near a path, in tiles (``tiled_world``), for
paths kilometres long.

The content follows the recipes of ``environments`` (the same shapes, sizes, materials and
densities per square metre), made local so that a tile depends only on its place, the seed
and the path:

- smooth fields (ground, roughness, grass and scrub heights) are value noise on a lattice fixed
  in world coordinates, its values hashed from (seed, lattice point): continuous across tiles;
- objects scattered over the area are drawn per tile, from a stream keyed by (seed, tile), and
  stamped into every tile they reach; objects strung along the path (the maze's corridor bites
  and clumps) are drawn once along the whole path.

So the worlds of a path and of any prefix of it agree wherever both have tiles, and a revisit
sees the same terrain.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from gslam_jax.sim.environments import (_GROUND, _KIND_IDS, WORLD_KINDS, paint_grass,
                                        paint_scrub)
from gslam_jax.sim.tiled_world import TiledWorld, corridor_tiles, densify
from gslam_jax.sim.world import (Material, World, stamp_box, stamp_canopy, stamp_clump,
                                 stamp_disk, stamp_dome)

__all__ = ["make_corridor_world"]


# ---- position-keyed randomness ---------------------------------------------------------------

def _mix(z: np.ndarray) -> np.ndarray:
    """The splitmix64 finaliser (uint64 arrays wrap on overflow)."""
    z = np.multiply(z ^ (z >> np.uint64(30)), np.uint64(0xBF58476D1CE4E5B9), dtype=np.uint64)
    z = np.multiply(z ^ (z >> np.uint64(27)), np.uint64(0x94D049BB133111EB), dtype=np.uint64)
    return z ^ (z >> np.uint64(31))


def _lattice_noise(key: int, x0: float, y0: float, res: float, n: int,
                   cell_m: float) -> np.ndarray:
    """Value noise in [0, 1) on the n x n pixels from (x0, y0): uniforms hashed from ``key`` at
    the points of a lattice of ``cell_m`` metres fixed in the world, bilinearly interpolated."""
    u = (x0 + (np.arange(n) + 0.5) * res) / cell_m
    v = (y0 + (np.arange(n) + 0.5) * res) / cell_m
    iu, iv = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    fu, fv = u - iu, v - iv
    gu = np.arange(iu[0], iu[-1] + 2).astype(np.uint64)
    gv = np.arange(iv[0], iv[-1] + 2).astype(np.uint64)
    z = np.multiply(gu[:, None], np.uint64(0x9E3779B97F4A7C15), dtype=np.uint64) + gv[None, :]
    lattice = (_mix(_mix(z) ^ np.uint64(key)) >> np.uint64(11)).astype(np.float64) / 2.0 ** 53
    a, b = iu - iu[0], iv - iv[0]
    rows = lattice[a] * (1.0 - fu)[:, None] + lattice[a + 1] * fu[:, None]
    return (rows[:, b] * (1.0 - fv) + rows[:, b + 1] * fv).astype(np.float32)


class _Stamp(NamedTuple):
    """One object: ``draw(world, x, y, *args)`` (and the tile's stream when ``random``);
    ``reach``: its radius from (x, y)."""

    draw: Callable | None
    x: float
    y: float
    reach: float
    args: tuple
    random: bool = False


class _Context:
    """What every tile of one world shares: its seed and kind, the path and the objects."""

    def __init__(self, kind: str, seed: int, path: np.ndarray, res: float, tile_px: int,
                 clearance: float) -> None:
        self.kind, self.seed, self.res, self.tile_px = kind, int(seed), res, tile_px
        self.tile_m = tile_px * res
        self.clearance = clearance
        self.path = densify(path, 0.1)
        self.tree = cKDTree(self.path)
        self._objects: dict[tuple[int, int], list[_Stamp]] = {}
        self.along: dict[tuple[int, int], list[_Stamp]] = {}  # objects strung along the path
        self.bites: dict[tuple[int, int], list[_Stamp]] = {}  # discs cut out of the maze's scrub

    def _seq(self, *words: int) -> np.random.SeedSequence:
        return np.random.SeedSequence([self.seed, _KIND_IDS[self.kind], 0xC0881D0,
                                       *(int(w) % 2 ** 32 for w in words)])

    def rng(self, stream: int, a: int = 0, b: int = 0) -> np.random.Generator:
        return np.random.default_rng(self._seq(stream, a, b))

    def field(self, number: int, x0: float, y0: float, cell_m: float) -> np.ndarray:
        key = int(self._seq(0xF1E1D, number).generate_state(1, np.uint64)[0])
        return _lattice_noise(key, x0, y0, self.res, self.tile_px, cell_m)

    def distance(self, xy: np.ndarray) -> np.ndarray:
        """Distance (m) from points [N, 2] to the path."""
        return self.tree.query(np.asarray(xy).reshape(-1, 2))[0] if len(xy) else np.zeros(0)

    def objects(self, a: int, b: int) -> list[_Stamp]:
        """The objects scattered over tile (a, b), drawn once."""
        if (a, b) not in self._objects:
            rng = self.rng(1, a, b)
            t = self.tile_m

            def uniform(density: float) -> np.ndarray:
                n = rng.poisson(density * t * t)
                return np.stack([a * t + rng.uniform(0.0, t, n),
                                 b * t + rng.uniform(0.0, t, n)], axis=1)

            self._objects[(a, b)] = _SCATTER[self.kind](self, rng, uniform)
        return self._objects[(a, b)]

    def add_along(self, table: dict[tuple[int, int], list[_Stamp]], stamp: _Stamp) -> None:
        key = (int(np.floor(stamp.x / self.tile_m)), int(np.floor(stamp.y / self.tile_m)))
        table.setdefault(key, []).append(stamp)


# ---- the three kinds (recipes of environments.py, per square metre) ---------------------------

def _grass(tile: World, ctx: _Context, rng: np.random.Generator, mean: float, spread: float,
           sandy_fraction: float) -> None:
    x0, y0 = tile.origin
    paint_grass(tile, ctx.field(2, x0, y0, 6.0), ctx.field(3, x0, y0, 9.0) < sandy_fraction,
                rng, mean, spread)


def _mars_yard_fields(tile: World, ctx: _Context, rng: np.random.Generator) -> None:
    tile.rough[:] = 0.003 + 0.006 * ctx.field(4, *tile.origin, 4.0)


def _mars_yard_objects(ctx: _Context, rng: np.random.Generator, uniform) -> list[_Stamp]:
    c, out = ctx.clearance, []
    xy = uniform(0.12)  # rocks: many pebbles, fewer boulders (log-normal radii)
    r = np.clip(rng.lognormal(np.log(0.12), 0.6, len(xy)), 0.04, 0.6)
    ok = ctx.distance(xy) >= c + r
    for (x, y), rr in zip(xy[ok], r[ok]):
        out.append(_Stamp(stamp_dome, x, y, rr, (rr, rr * rng.uniform(0.6, 1.0),
                          rng.uniform(0, np.pi), rr * rng.uniform(0.5, 0.9), 0.01, Material.ROCK)))
    # traffic poles: a band lining the path (one per ~3.5 m of path), a few scattered
    lining, far = uniform(0.06), uniform(0.01)
    d_lining, d_far = ctx.distance(lining), ctx.distance(far)
    poles = np.concatenate([lining[(d_lining >= c + 0.15) & (d_lining <= c + 2.5)],
                            far[d_far > c + 2.5]])
    for x, y in poles:
        out.append(_Stamp(stamp_disk, x, y, 0.1, (rng.uniform(0.06, 0.1), rng.uniform(0.9, 1.15),
                                                  0.004, Material.POLE)))
        out.append(_Stamp(stamp_disk, x, y, 0.18, (0.18, 0.04, 0.004, Material.POLE)))
    xy = uniform(1.0 / 40.0)  # storage bins, single or stacked
    for x, y in xy[ctx.distance(xy) >= c + 0.5]:
        out.append(_Stamp(stamp_box, x, y, 0.38, (0.62, 0.44, rng.uniform(0, np.pi),
                                                  0.42 * rng.choice([1, 1, 2]), 0.004,
                                                  Material.BIN)))
    for x, y in uniform(0.001):  # buildings beside the path
        lx, ly = rng.uniform(6.0, 10.0), rng.uniform(4.0, 6.0)
        corners = np.array([[x + i * lx / 2, y + j * ly / 2] for i in (-1, 0, 1)
                            for j in (-1, 0, 1)])
        if ctx.distance(corners).min() >= c + 2.0:
            out.append(_Stamp(stamp_box, x, y, 0.5 * np.hypot(lx, ly),
                              (lx, ly, 0.0, 3.0, 0.005, Material.BUILDING)))
    return out


def _arroyo_fields(tile: World, ctx: _Context, rng: np.random.Generator) -> None:
    _grass(tile, ctx, rng, mean=0.16, spread=0.28, sandy_fraction=0.3)


def _arroyo_objects(ctx: _Context, rng: np.random.Generator, uniform) -> list[_Stamp]:
    c, out = ctx.clearance, []
    xy = uniform(0.05)  # bushes: spindly to dense
    radius = rng.uniform(0.3, 1.4, len(xy))
    for (x, y), r, dp in zip(xy, radius, ctx.distance(xy)):
        r_eff = min(r, dp - c)
        if r_eff < 0.25:
            continue
        out.append(_Stamp(stamp_clump, x, y, r_eff, (r_eff, rng.uniform(0.4, 1.7),
                                                     rng.uniform(0.2, 0.95), 0.12,
                                                     Material.BUSH), True))
    xy = uniform(0.004)  # trees: trunk plus a crown above the overhang band
    for x, y in xy[ctx.distance(xy) >= c + 0.6]:
        lo = rng.uniform(2.6, 3.4)
        out.append(_Stamp(stamp_disk, x, y, 0.25, (rng.uniform(0.12, 0.25), lo + 0.8, 0.02,
                                                   Material.TREE)))
        crown = rng.uniform(1.8, 3.5)
        out.append(_Stamp(stamp_canopy, x, y, crown, (crown, lo, lo + rng.uniform(1.5, 2.5),
                                                      0.75), True))
    xy = uniform(0.01)  # a few rocks
    r = rng.uniform(0.1, 0.4, len(xy))
    ok = ctx.distance(xy) >= c + r
    for (x, y), rr in zip(xy[ok], r[ok]):
        out.append(_Stamp(stamp_dome, x, y, rr, (rr, rr, 0.0, 0.7 * rr, 0.01, Material.ROCK)))
    return out


def _maze_along(ctx: _Context, path: np.ndarray) -> None:
    """Bites out of the corridor edges (one per ~4 m) and clumps in the corridors (one per
    ~5 m), drawn along the whole path."""
    rng, c = ctx.rng(2), ctx.clearance
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(path, axis=0).T))])
    n = int(s[-1] / 4.0)
    i = np.searchsorted(s, rng.uniform(0.0, s[-1], n)).clip(1, len(s) - 1)
    t = path[i] - path[i - 1]
    nrm = np.stack([-t[:, 1], t[:, 0]], 1) / np.maximum(np.hypot(*t.T), 1e-9)[:, None]
    centre = path[i] + (rng.choice([-1.0, 1.0], n) * rng.uniform(1.3, 2.0, n))[:, None] * nrm
    for (x, y), r in zip(centre, rng.uniform(0.4, 1.1, n)):
        ctx.add_along(ctx.bites, _Stamp(None, x, y, r, ()))
    n = int(s[-1] / 5.0)
    xy = path[rng.integers(0, len(path), n)] + rng.uniform(-1.6, 1.6, (n, 2))
    r = rng.uniform(0.15, 0.4, n)
    height = rng.uniform(0.3, 0.9, n)
    ok = ctx.distance(xy) >= r + c
    for (x, y), rr, h in zip(xy[ok], r[ok], height[ok]):
        ctx.add_along(ctx.along, _Stamp(stamp_clump, x, y, rr, (rr, h, 0.85, 0.1, Material.BUSH),
                                        True))


def _maze_fields(tile: World, ctx: _Context, rng: np.random.Generator) -> None:
    _grass(tile, ctx, rng, mean=0.07, spread=0.08, sandy_fraction=0.15)
    x0, y0 = tile.origin
    n, res, radius = tile.shape[0], tile.resolution, ctx.clearance + 0.3
    g = (np.arange(n) + 0.5) * res
    corridor = np.zeros(tile.shape, bool)  # the path's clearance, then the bites
    half = 0.5 * ctx.tile_m
    if ctx.distance(np.array([[x0 + half, y0 + half]]))[0] <= radius + half * np.sqrt(2) + 0.1:
        pix = np.stack(np.meshgrid(x0 + g, y0 + g, indexing="ij"), -1).reshape(-1, 2)
        d = ctx.tree.query(pix, distance_upper_bound=radius + 0.1)[0]
        corridor = (d <= radius).reshape(tile.shape)
    for bite in _near(ctx, tile, ctx.bites):  # irregular corridor edges
        corridor |= ((x0 + g - bite.x)[:, None] ** 2 + (y0 + g - bite.y)[None, :] ** 2
                     <= bite.reach ** 2)
    paint_scrub(tile, ctx.field(5, x0, y0, 5.0), corridor, rng)


def _maze_objects(ctx: _Context, rng: np.random.Generator, uniform) -> list[_Stamp]:
    return []


_FIELDS = {"mars-yard": _mars_yard_fields, "arroyo": _arroyo_fields, "maze": _maze_fields}
_SCATTER = {"mars-yard": _mars_yard_objects, "arroyo": _arroyo_objects, "maze": _maze_objects}


def _near(ctx: _Context, tile: World,
          table: dict[tuple[int, int], list[_Stamp]] | None) -> list[_Stamp]:
    """The objects (of ``table``, or scattered when None) of the 3 x 3 tiles around ``tile``
    that reach into it."""
    a = int(round(tile.origin[0] / ctx.tile_m))
    b = int(round(tile.origin[1] / ctx.tile_m))
    x0, y0, t = a * ctx.tile_m, b * ctx.tile_m, ctx.tile_m
    out = []
    for da in (-1, 0, 1):
        for db in (-1, 0, 1):
            cell = ctx.objects(a + da, b + db) if table is None else table.get((a + da, b + db),
                                                                               [])
            out += [s for s in cell if x0 - s.reach <= s.x <= x0 + t + s.reach
                    and y0 - s.reach <= s.y <= y0 + t + s.reach]
    return out


def make_corridor_world(kind: str, seed: int, path: np.ndarray, *,
                        driven: np.ndarray | None = None, half_width: float = 12.0,
                        resolution: float = 0.05, clearance: float = 0.7,
                        tile_px: int = 128) -> TiledWorld:
    """A world of ``kind`` (one of ``WORLD_KINDS``) in tiles within ``half_width`` metres of
    ``driven`` (default: all of ``path``), objects kept ``clearance`` m off the whole ``path``
    [N, 2]. ``half_width`` must exceed the sensor's range; ``tile_px`` is a power of two."""
    if kind not in _FIELDS:
        raise ValueError(f"unknown world kind {kind!r}; valid kinds: {', '.join(WORLD_KINDS)}")
    if tile_px < 8 or tile_px & (tile_px - 1):
        raise ValueError(f"tile_px must be a power of two >= 8, got {tile_px}")
    if not half_width > 0 or not resolution > 0 or clearance < 0:
        raise ValueError(f"need half_width > 0, resolution > 0, clearance >= 0; got "
                         f"{half_width}, {resolution}, {clearance}")
    path = np.asarray(path, np.float64)
    ctx = _Context(kind, seed, path, resolution, tile_px, clearance)
    tiles = corridor_tiles(path if driven is None else driven, half_width, ctx.tile_m)
    slots = len(tiles) + 1
    if slots * tile_px * tile_px >= 2 ** 31:
        raise ValueError(f"{len(tiles)} tiles of {tile_px} px exceed the int32 pixel index")
    lo = tiles.min(axis=0)
    table = np.zeros(tuple(tiles.max(axis=0) - lo + 1), np.int32)
    table[tiles[:, 0] - lo[0], tiles[:, 1] - lo[1]] = np.arange(1, slots, dtype=np.int32)
    shape = (slots, tile_px, tile_px)
    if kind == "arroyo":
        canopy_lo = np.full(shape, np.inf, np.float32)
        canopy_hi = np.full(shape, -np.inf, np.float32)
    else:
        canopy_lo = np.broadcast_to(np.full((1, tile_px, tile_px), np.inf, np.float32), shape)
        canopy_hi = np.broadcast_to(np.full((1, tile_px, tile_px), -np.inf, np.float32), shape)
    world = TiledWorld(kind=kind, seed=int(seed), resolution=resolution,
                       origin=(float(lo[0] * ctx.tile_m), float(lo[1] * ctx.tile_m)),
                       ground=np.zeros(shape, np.float32), height=np.zeros(shape, np.float32),
                       rough=np.full(shape, 0.005, np.float32), canopy_lo=canopy_lo,
                       canopy_hi=canopy_hi, material=np.zeros(shape, np.uint8), tiles=table,
                       tile_px=tile_px)
    if kind == "maze":
        _maze_along(ctx, ctx.path)
    amp, scale = _GROUND[kind]
    for slot, (a, b) in enumerate(tiles, 1):
        tile = World(kind=kind, seed=int(seed), resolution=resolution,
                     origin=(float(a * ctx.tile_m), float(b * ctx.tile_m)),
                     ground=world.ground[slot], height=world.height[slot],
                     rough=world.rough[slot], canopy_lo=world.canopy_lo[slot],
                     canopy_hi=world.canopy_hi[slot], material=world.material[slot])
        tile.ground[:] = amp * (ctx.field(1, *tile.origin, scale) - 0.5)
        tile.height[:] = tile.ground
        rng = ctx.rng(3, a, b)
        _FIELDS[kind](tile, ctx, rng)
        for stamp in _near(ctx, tile, None) + _near(ctx, tile, ctx.along):
            extra = (rng,) if stamp.random else ()
            stamp.draw(tile, stamp.x, stamp.y, *stamp.args, *extra)
    return world
