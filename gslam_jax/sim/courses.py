"""Courses after the paper's Table I: smooth closed paths of known length through a world.

A course is a polyline sampled every 5 cm, built from a seeded control polygon, corner-cut
(Chaikin) into a smooth curve and scaled to the Table I distance. It also names the world kind it
runs through, where the robot stops for surveys, and hints for the world generator (zones of dense
vegetation, extra side corridors).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

__all__ = ["CourseSpec", "Course", "COURSES", "course_names", "make_course", "resample_path",
           "path_length", "course_from_path"]

_STEP = 0.05  # path sampling, metres


@dataclass(frozen=True)
class CourseSpec:
    """Static description of a Table I course."""

    name: str
    kind: str  # world kind: "mars-yard", "arroyo" or "maze"
    length: float  # metres (Table I)
    loops: int
    description: str
    survey_every: float = 25.0  # metres between survey stops


@dataclass
class Course:
    """A concrete, seeded course.

    path: [N, 2] world positions every ~5 cm (start = end within a few metres).
    s: [N] arc length (m); heading: [N] tangent direction (rad, unwrapped).
    survey_s: arc lengths of the survey stops (the start and the end included).
    dense_zones: [(x, y, radius)] where the world should grow dense vegetation.
    side_corridors: extra polylines the world keeps open (maze offshoots).
    """

    spec: CourseSpec
    seed: int
    path: np.ndarray
    s: np.ndarray
    heading: np.ndarray
    survey_s: np.ndarray
    dense_zones: list[tuple[float, float, float]] = field(default_factory=list)
    side_corridors: list[np.ndarray] = field(default_factory=list)

    @property
    def length(self) -> float:
        return float(self.s[-1])


def path_length(xy: np.ndarray) -> float:
    return float(np.sum(np.hypot(*np.diff(np.asarray(xy), axis=0).T)))


def resample_path(xy: np.ndarray, step: float = _STEP) -> np.ndarray:
    """Resample a polyline at (nearly) uniform arc-length spacing, keeping both ends."""
    xy = np.asarray(xy, dtype=np.float64)
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    n = max(int(np.ceil(s[-1] / step)), 1)
    ss = np.linspace(0.0, s[-1], n + 1)
    return np.stack([np.interp(ss, s, xy[:, 0]), np.interp(ss, s, xy[:, 1])], axis=1)


def _chaikin(xy: np.ndarray, iterations: int) -> np.ndarray:
    """Corner cutting on an open polyline (ends kept): converges to a quadratic B-spline."""
    for _ in range(iterations):
        a, b = xy[:-1], xy[1:]
        q = 0.75 * a + 0.25 * b
        r = 0.25 * a + 0.75 * b
        mid = np.stack([q, r], axis=1).reshape(-1, 2)
        xy = np.concatenate([xy[:1], mid[1:-1], xy[-1:]])
    return xy


def _densify(xy: np.ndarray, max_seg: float) -> np.ndarray:
    out = [xy[:1]]
    for a, b in zip(xy[:-1], xy[1:]):
        n = max(int(np.ceil(np.hypot(*(b - a)) / max_seg)), 1)
        t = np.arange(1, n + 1)[:, None] / n
        out.append(a + t * (b - a))
    return np.concatenate(out)


def _smooth_to_length(poly: np.ndarray, length: float, densify: float | None,
                      iterations: int = 5) -> tuple[np.ndarray, float]:
    """Scale, smooth and rescale a control polygon (start at the origin) to ``length`` m."""
    poly = np.asarray(poly, dtype=np.float64)
    poly = poly - poly[0]
    scale = length / path_length(poly)
    xy = poly * scale
    if densify is not None:
        xy = _densify(xy, densify)
    xy = resample_path(_chaikin(xy, iterations))
    final = length / path_length(xy)
    return resample_path(xy * final), scale * final


# Control polygons, in arbitrary units (scaled to the Table I length afterwards).

def _mars_yard_a(rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """Back and forth over the same strip of yard: three narrow elongated loops."""
    pts: list[tuple[float, float]] = [(0.0, 0.0)]
    for lane_len, width in ((22.0, 3.0), (19.0, 2.4), (21.0, 3.6)):
        lane_len += rng.uniform(-0.5, 0.5)
        out = [(x, rng.normal(0.0, 0.25)) for x in np.linspace(4.0, lane_len - 3.0, 4)]
        back = [(x, width + rng.normal(0.0, 0.25)) for x in np.linspace(lane_len - 3.0, 4.0, 4)]
        pts += out + [(lane_len, 0.0), (lane_len + 1.6, 0.5 * width), (lane_len, width)]
        pts += back + [(0.0, width), (-1.6, 0.5 * width), (0.0, 0.0)]
    return np.asarray(pts), {}


def _loop(rng: np.random.Generator, rx: float, ry: float, n: int, wobble: float,
          phase: float = -np.pi / 2) -> list[tuple[float, float]]:
    """Vertices of a wobbly ellipse starting (and ending) at its bottom point."""
    ang = phase + np.linspace(0.0, 2 * np.pi, n + 1)
    r = 1.0 + rng.normal(0.0, wobble, n + 1)
    r[0] = r[-1] = 1.0
    return [(rx * rr * np.cos(a), ry * rr * np.sin(a) + ry) for a, rr in zip(ang, r)]


def _squarish(rx: float, ry: float, rng: np.random.Generator,
              jit: float) -> list[tuple[float, float]]:
    """A rounded rectangle's control points from the middle of its bottom side."""
    p = [(0, 0), (rx, 0), (rx, 2 * ry), (-rx, 2 * ry), (-rx, 0), (0, 0)]
    return [(x + rng.normal(0, jit), y + rng.normal(0, jit)) if 0 < i < 5 else (x, y)
            for i, (x, y) in enumerate(p)]


def _mars_yard_b(rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """Three large loops around the yard."""
    pts: list[tuple[float, float]] = []
    for k in range(3):
        loop = _squarish(11.0 + 0.6 * k, 5.5 - 0.4 * k, rng, 0.6)
        pts += loop if not pts else loop[1:]
    return np.asarray(pts), {}


def _arroyo_a(rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """Three loops around a mostly open field."""
    pts: list[tuple[float, float]] = []
    for k in range(3):
        loop = _loop(rng, 18.0 + rng.uniform(-1, 1), 11.0 + rng.uniform(-1, 1), 9, 0.05)
        pts += loop if not pts else loop[1:]
    return np.asarray(pts), {}


def _arroyo_b(rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """Two loops, each with a diversion (a lobe) into dense vegetation."""
    base = _loop(rng, 22.0, 13.0, 10, 0.04)
    n = len(base) - 1
    pts: list[tuple[float, float]] = []
    lobes = []
    for k, at in enumerate((3, 7)):  # after vertex `at`, detour outward
        loop = list(base) if k == 0 else [(x + rng.normal(0, 0.6), y + rng.normal(0, 0.6))
                                          for x, y in base]
        loop[0] = loop[-1] = base[0]
        a, b = np.asarray(loop[at]), np.asarray(loop[(at + 1) % n])
        mid = 0.5 * (a + b)
        centre = np.array([0.0, 13.0])
        out = (mid - centre) / np.linalg.norm(mid - centre)
        side = np.array([-out[1], out[0]])
        depth = 10.0
        lobe = [tuple(a + 2.0 * out), tuple(mid + depth * out - 2.5 * side),
                tuple(mid + (depth + 3.0) * out), tuple(mid + depth * out + 2.5 * side),
                tuple(b + 2.0 * out)]
        lobes.append(tuple(mid + (depth * 0.7) * out))
        seq = loop[:at + 1] + lobe + loop[at + 1:]
        pts += seq if not pts else seq[1:]
    return np.asarray(pts), {"lobes": lobes}


_MAZE_LOOPS = (
    [(0, 0), (3, 0), (3, 2), (0, 2), (0, 0)],
    [(0, 0), (1, 0), (1, 1), (2, 1), (2, 2), (0, 2), (0, 0)],
    [(0, 0), (2, 0), (2, 1), (3, 1), (3, 2), (1, 2), (1, 1), (0, 1), (0, 0)],
    [(0, 0), (3, 0), (3, 1), (1, 1), (1, 2), (0, 2), (0, 0)],
)


def _maze(rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """Four loops through a grid of corridors cut into scrub (3 x 2 blocks)."""
    cell = 14.0
    pts: list[tuple[float, float]] = []
    for loop in _MAZE_LOOPS:
        seq = [(cell * i + rng.normal(0, 0.15) * (0 < n < len(loop) - 1),
                cell * j + rng.normal(0, 0.15) * (0 < n < len(loop) - 1))
               for n, (i, j) in enumerate(loop)]
        pts += seq if not pts else seq[1:]
    return np.asarray(pts), {"densify": 1.5}


_BUILDERS: dict[str, Callable[[np.random.Generator], tuple[np.ndarray, dict]]] = {
    "mars-yard-a": _mars_yard_a,
    "mars-yard-b": _mars_yard_b,
    "arroyo-a": _arroyo_a,
    "arroyo-b": _arroyo_b,
    "maze": _maze,
}

COURSES: dict[str, CourseSpec] = {
    "mars-yard-a": CourseSpec("mars-yard-a", "mars-yard", 164.0, 3,
                              "Mars Yard A: back and forth over the same terrain, three loops"),
    "mars-yard-b": CourseSpec("mars-yard-b", "mars-yard", 204.0, 3,
                              "Mars Yard B: three large loops around the yard"),
    "arroyo-a": CourseSpec("arroyo-a", "arroyo", 335.0, 3,
                           "Arroyo Seco A: three loops around a mostly open field"),
    "arroyo-b": CourseSpec("arroyo-b", "arroyo", 406.0, 2,
                           "Arroyo Seco B: two loops with diversions into dense vegetation"),
    "maze": CourseSpec("maze", "maze", 543.0, 4,
                       "SwRI maze: four loops on narrow paths cut through dense scrub",
                       survey_every=60.0),
}


def course_names() -> list[str]:
    return list(COURSES)


def make_course(name: str, seed: int = 0) -> Course:
    """Build the course ``name`` (one of ``course_names()``) for ``seed``."""
    if name not in COURSES:
        raise ValueError(f"unknown course {name!r}; valid courses: {', '.join(COURSES)}")
    spec = COURSES[name]
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xC0]))
    poly, hints = _BUILDERS[name](rng)
    path, scale = _smooth_to_length(poly, spec.length, hints.get("densify"),
                                    iterations=3 if "densify" in hints else 5)
    d = np.diff(path, axis=0)
    heading = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    heading = np.concatenate([heading, heading[-1:]])
    s = np.concatenate([[0.0], np.cumsum(np.hypot(d[:, 0], d[:, 1]))])
    n_surveys = max(int(round(s[-1] / spec.survey_every)), 1)
    survey_s = np.linspace(0.0, s[-1], n_surveys + 1)
    poly0 = poly - poly[0]
    zones = [(float(x * scale), float(y * scale), 6.0)
             for x, y in (np.asarray(hints.get("lobes", []), float).reshape(-1, 2) - poly[0])]
    corridors = []
    if spec.kind == "maze":
        corridors = _maze_offshoots(rng, poly0 * scale)
    return Course(spec=spec, seed=int(seed), path=path, s=s, heading=heading, survey_s=survey_s,
                  dense_zones=zones, side_corridors=corridors)


def _maze_offshoots(rng: np.random.Generator, poly: np.ndarray) -> list[np.ndarray]:
    """Dead-end corridors branching off the maze's corridor grid (never driven)."""
    nodes = np.unique(np.round(poly, 0), axis=0)
    out = []
    for _ in range(10):
        a = nodes[rng.integers(len(nodes))]
        b = nodes[rng.integers(len(nodes))]
        if np.allclose(a, b):
            continue
        # branch from a point on an axis-aligned segment between two grid nodes
        t = rng.uniform(0.25, 0.75)
        start = a + t * (np.array([b[0], a[1]]) - a)
        direction = np.array([0.0, 1.0]) if abs(b[0] - a[0]) > 1 else np.array([1.0, 0.0])
        direction *= rng.choice([-1.0, 1.0])
        out.append(np.stack([start, start + rng.uniform(3.0, 8.0) * direction]))
    return out


def course_from_path(xy: np.ndarray, name: str, kind: str, description: str, seed: int = 0, *,
                     spacing: float = 0.5, iterations: int = 3) -> Course:
    """A course along a given planar path ``xy`` [N, 2] (e.g. a recorded trajectory).

    Repeated points (a vehicle standing still) are dropped; the path is resampled every
    ``spacing`` metres and corner-cut (Chaikin, ``iterations``) so the heading turns smoothly
    between a recording's vertices (corners move by a fraction of ``spacing``), then sampled
    every 5 cm like every course. Survey stops only at the start and the end.
    """
    xy = np.asarray(xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2 or not np.all(np.isfinite(xy)):
        raise ValueError(f"path must be finite [N, 2] positions, got shape {xy.shape}")
    keep = np.concatenate([[True], np.hypot(*np.diff(xy, axis=0).T) > 1e-6])
    xy = xy[keep]
    length = path_length(xy)
    if length < 4 * spacing:
        raise ValueError(f"path {name!r} is {length:.2f} m long; a course needs at least "
                         f"{4 * spacing:g} m")
    path = resample_path(_chaikin(resample_path(xy, spacing), iterations))
    d = np.diff(path, axis=0)
    heading = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    heading = np.concatenate([heading, heading[-1:]])
    s = np.concatenate([[0.0], np.cumsum(np.hypot(d[:, 0], d[:, 1]))])
    spec = CourseSpec(name, kind, float(s[-1]), 0, description, survey_every=float(s[-1]))
    return Course(spec=spec, seed=int(seed), path=path, s=s, heading=heading,
                  survey_s=np.array([0.0, s[-1]]))
