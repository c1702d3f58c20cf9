"""Procedural worlds of the paper's three environments (section 7), built around a course.

- "mars-yard": flat sand with gentle undulation, rocks of all sizes, orange traffic poles,
  plastic storage bins, two buildings beside the course.
- "arroyo": undulating ground, grass of varying height with sandy patches, bushes from spindly to
  dense (dense thickets around the course's diversion zones), trees whose crowns overhang.
- "maze": dense scrub everywhere except narrow corridors along the course and a few dead-end
  offshoots; corridor edges are irregular.

Objects never come closer than ``clearance`` metres to the path, so the robot drives free.
Everything is drawn from one ``numpy.random.Generator`` seeded by (seed, kind): same seed, same
world.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from gslam_jax.sim.courses import Course
from gslam_jax.sim.world import (Material, World, empty_world, path_clearance_mask, smooth_noise, stamp_box,
                    stamp_canopy, stamp_clump, stamp_disk, stamp_dome)

__all__ = ["WORLD_KINDS", "make_world", "world_for_course"]

_KIND_IDS = {"mars-yard": 1, "arroyo": 2, "maze": 3}
WORLD_KINDS = tuple(_KIND_IDS)


def _distance_to_path(points: np.ndarray, path_xy: np.ndarray, spacing: float = 0.2) -> np.ndarray:
    """Distance (m) from each of ``points`` [N, 2] to the polyline (approximated at ``spacing``)."""
    d = np.hypot(*np.diff(path_xy, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(d)])
    ss = np.arange(0.0, s[-1] + spacing, spacing)
    ref = np.stack([np.interp(ss, s, path_xy[:, 0]), np.interp(ss, s, path_xy[:, 1])], axis=1)
    out = np.empty(len(points))
    for a in range(0, len(points), 256):
        q = points[a:a + 256]
        out[a:a + 256] = np.sqrt(((q[:, None, :] - ref[None]) ** 2).sum(-1).min(1))
    return out


def _ground(rng: np.random.Generator, shape: tuple[int, int], res: float, amplitude: float,
            scale_m: float) -> np.ndarray:
    return (amplitude * (smooth_noise(shape, scale_m / res, rng) - 0.5)).astype(np.float32)


def _mars_yard(world: World, course: Course, rng: np.random.Generator, clearance: float) -> None:
    path, res = course.path, world.resolution
    area = (world.extent[1] - world.extent[0]) * (world.extent[3] - world.extent[2])
    world.rough[:] = 0.003 + 0.006 * smooth_noise(world.shape, 4.0 / res, rng)
    # rocks: many pebbles, fewer boulders (log-normal radii)
    n = int(area * 0.12)
    r = np.clip(rng.lognormal(np.log(0.12), 0.6, n), 0.04, 0.6)
    xy = np.stack([rng.uniform(world.extent[0], world.extent[1], n),
                   rng.uniform(world.extent[2], world.extent[3], n)], axis=1)
    ok = _distance_to_path(xy, path) >= clearance + r
    for (x, y), rr in zip(xy[ok], r[ok]):
        stamp_dome(world, x, y, rr, rr * rng.uniform(0.6, 1.0), rng.uniform(0, np.pi),
                   rr * rng.uniform(0.5, 0.9), 0.01, Material.ROCK)
    # traffic poles: mostly lining the course, some scattered
    near = int(course.length / 3.5)
    xy = np.stack([rng.uniform(world.extent[0], world.extent[1], 8 * near),
                   rng.uniform(world.extent[2], world.extent[3], 8 * near)], axis=1)
    d = _distance_to_path(xy, path)
    lining = np.flatnonzero((d >= clearance + 0.15) & (d <= clearance + 2.5))[:near]
    far = np.flatnonzero(d > clearance + 2.5)[: near // 3]
    for x, y in xy[np.concatenate([lining, far])]:
        stamp_disk(world, x, y, rng.uniform(0.06, 0.1), rng.uniform(0.9, 1.15), 0.004,
                   Material.POLE)
        stamp_disk(world, x, y, 0.18, 0.04, 0.004, Material.POLE)  # weighted base
    # storage bins, single or stacked
    n = int(area / 40)
    xy = np.stack([rng.uniform(world.extent[0], world.extent[1], n),
                   rng.uniform(world.extent[2], world.extent[3], n)], axis=1)
    ok = _distance_to_path(xy, path) >= clearance + 0.5
    for x, y in xy[ok]:
        stamp_box(world, x, y, 0.62, 0.44, rng.uniform(0, np.pi),
                  0.42 * rng.choice([1, 1, 2]), 0.004, Material.BIN)
    # two buildings beside the course, on opposite sides of it
    centre = path.mean(axis=0)
    for side in (-1.0, 1.0):
        for _ in range(200):
            lx, ly = rng.uniform(6.0, 10.0), rng.uniform(4.0, 6.0)
            x = centre[0] + rng.uniform(-0.4, 0.4) * (world.extent[1] - world.extent[0])
            y = centre[1] + side * rng.uniform(0.15, 0.45) * (world.extent[3] - world.extent[2])
            corners = np.array([[x + a * lx / 2, y + b * ly / 2] for a in (-1, 0, 1)
                                for b in (-1, 0, 1)])
            if _distance_to_path(corners, path).min() >= clearance + 2.0:
                stamp_box(world, x, y, lx, ly, 0.0, 3.0, 0.005, Material.BUILDING)
                break


def _grass(world: World, rng: np.random.Generator, res: float, mean: float, spread: float,
           sandy_fraction: float) -> None:
    field = smooth_noise(world.shape, 6.0 / res, rng)
    sandy = smooth_noise(world.shape, 9.0 / res, rng) < sandy_fraction
    paint_grass(world, field, sandy, rng, mean, spread)


def paint_scrub(world: World, field: np.ndarray, corridor: np.ndarray,
                rng: np.random.Generator) -> None:
    """Dense scrub 0.9-2 m tall (by the smooth ``field`` in [0, 1]) everywhere off the
    ``corridor`` mask, with a few gaps."""
    top = 0.9 + 1.1 * field
    per_px = top * rng.uniform(0.65, 1.0, world.shape).astype(np.float32)
    present = (~corridor) & (rng.random(world.shape) < 0.92)
    world.height[present] = np.maximum(world.height[present],
                                       world.ground[present] + per_px[present])
    world.rough[present] = 0.15
    world.material[present] = int(Material.SCRUB)


def paint_grass(world: World, field: np.ndarray, sandy: np.ndarray, rng: np.random.Generator,
                mean: float, spread: float) -> None:
    """Grass blades over the ground outside the ``sandy`` patches, their height set by the
    smooth ``field`` in [0, 1] around ``mean`` (spread ``spread``), rough in proportion."""
    gh = (mean + spread * (field - 0.5)).clip(0.02, None)
    blade = gh * rng.uniform(0.3, 1.0, world.shape).astype(np.float32)
    grass = ~sandy
    world.height[grass] = world.ground[grass] + blade[grass]
    world.rough[grass] = 0.3 * gh[grass]
    world.material[grass] = int(Material.GRASS)


def _arroyo(world: World, course: Course, rng: np.random.Generator, clearance: float) -> None:
    path, res = course.path, world.resolution
    area = (world.extent[1] - world.extent[0]) * (world.extent[3] - world.extent[2])
    _grass(world, rng, res, mean=0.16, spread=0.28, sandy_fraction=0.3)
    # bushes: spindly to dense
    n = int(area * 0.05)
    xy = np.stack([rng.uniform(world.extent[0], world.extent[1], n),
                   rng.uniform(world.extent[2], world.extent[3], n)], axis=1)
    for zx, zy, zr in course.dense_zones:  # thickets around the diversions
        m = int(zr * zr * 1.2)
        ang, rad = rng.uniform(0, 2 * np.pi, m), zr * np.sqrt(rng.uniform(0, 1, m))
        xy = np.concatenate([xy, np.stack([zx + rad * np.cos(ang), zy + rad * np.sin(ang)], 1)])
    radius = rng.uniform(0.3, 1.4, len(xy))
    dist = _distance_to_path(xy, path)
    in_zone = np.zeros(len(xy), bool)
    for zx, zy, zr in course.dense_zones:
        in_zone |= np.hypot(xy[:, 0] - zx, xy[:, 1] - zy) < zr + 2.0
    for (x, y), r, dz, dp in zip(xy, radius, in_zone, dist):
        r_eff = min(r, dp - clearance)
        if r_eff < 0.25:
            continue
        density = rng.uniform(0.8, 0.97) if dz else rng.uniform(0.2, 0.95)
        stamp_clump(world, x, y, r_eff, rng.uniform(0.4, 1.7), density, 0.12, Material.BUSH, rng)
    # trees: trunk plus a crown above the overhang band, which may overhang the path
    n = int(area * 0.004)
    xy = np.stack([rng.uniform(world.extent[0], world.extent[1], n),
                   rng.uniform(world.extent[2], world.extent[3], n)], axis=1)
    ok = _distance_to_path(xy, path) >= clearance + 0.6
    for x, y in xy[ok]:
        lo = rng.uniform(2.6, 3.4)
        stamp_disk(world, x, y, rng.uniform(0.12, 0.25), lo + 0.8, 0.02, Material.TREE)
        stamp_canopy(world, x, y, rng.uniform(1.8, 3.5), lo, lo + rng.uniform(1.5, 2.5),
                     0.75, rng)
    # a few rocks
    n = int(area * 0.01)
    xy = np.stack([rng.uniform(world.extent[0], world.extent[1], n),
                   rng.uniform(world.extent[2], world.extent[3], n)], axis=1)
    r = rng.uniform(0.1, 0.4, n)
    ok = _distance_to_path(xy, path) >= clearance + r
    for (x, y), rr in zip(xy[ok], r[ok]):
        stamp_dome(world, x, y, rr, rr, 0.0, 0.7 * rr, 0.01, Material.ROCK)


def _maze(world: World, course: Course, rng: np.random.Generator, clearance: float) -> None:
    path, res = course.path, world.resolution
    _grass(world, rng, res, mean=0.07, spread=0.08, sandy_fraction=0.15)
    corridor = path_clearance_mask(world, path, clearance + 0.3)
    for spur in course.side_corridors:
        corridor |= path_clearance_mask(world, spur, 0.8)
    # irregular corridor edges: bites out of the scrub along the path
    d = np.hypot(*np.diff(path, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(d)])
    for s0 in rng.uniform(0.0, s[-1], int(s[-1] / 4.0)):
        i = int(np.searchsorted(s, s0).clip(1, len(s) - 1))
        t = path[i] - path[i - 1]
        nrm = np.array([-t[1], t[0]]) / max(np.hypot(*t), 1e-9)
        c = path[i] + rng.choice([-1.0, 1.0]) * rng.uniform(1.3, 2.0) * nrm
        corridor |= path_clearance_mask(world, np.stack([c, c + 0.01 * nrm]),
                                        rng.uniform(0.4, 1.1))
    paint_scrub(world, smooth_noise(world.shape, 5.0 / res, rng), corridor, rng)
    # a few isolated clumps and rocks inside the corridors, off the driven line
    keep_clear = path_clearance_mask(world, path, clearance)
    n = int(course.length / 5.0)
    idx = rng.integers(0, len(path), n)
    off = rng.uniform(-1.6, 1.6, (n, 2))
    for (x, y), r in zip(path[idx] + off, rng.uniform(0.15, 0.4, n)):
        i, j = world.cell_of(np.array([x, y]))
        rr = r + clearance
        if keep_clear[i, j] or _distance_to_path(np.array([[x, y]]), path)[0] < rr:
            continue
        stamp_clump(world, x, y, r, rng.uniform(0.3, 0.9), 0.85, 0.1, Material.BUSH, rng)


_GENERATORS: dict[str, Callable[[World, Course, np.random.Generator, float], None]] = {
    "mars-yard": _mars_yard, "arroyo": _arroyo, "maze": _maze,
}

_GROUND = {"mars-yard": (0.25, 12.0), "arroyo": (0.6, 15.0), "maze": (0.4, 15.0)}


def make_world(kind: str, seed: int, course: Course, *, resolution: float = 0.05,
               margin: float = 12.0, clearance: float = 0.7) -> World:
    """Generate a world of ``kind`` around ``course`` (objects kept ``clearance`` m off the path).

    ``margin`` metres of world surround the path's bounding box (>= the sensor range).
    """
    if kind not in _GENERATORS:
        raise ValueError(f"unknown world kind {kind!r}; valid kinds: {', '.join(_GENERATORS)}")
    if clearance < 0:
        raise ValueError(f"clearance must be >= 0 m, got {clearance}")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), _KIND_IDS[kind], 0x5EED]))
    lo, hi = course.path.min(axis=0) - margin, course.path.max(axis=0) + margin
    bounds = (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]))
    world = empty_world(kind, int(seed), bounds, resolution)
    amp, scale = _GROUND[kind]
    world.ground[:] = _ground(rng, world.shape, resolution, amp, scale)
    world.height[:] = world.ground
    _GENERATORS[kind](world, course, rng, clearance)
    return world


def world_for_course(course: Course, seed: int, **kwargs) -> World:
    """The world a course runs through (its kind, seeded by ``seed``)."""
    return make_world(course.spec.kind, seed, course, **kwargs)
