"""The loops the loop experiments drive, as trajectory files for ``gslam run --course-path``
(``datasets.sim_path``): circles of a given perimeter, and cuts of KITTI pose files between a
pose and its first return that hold no shorter loop.

The revisit the experiments score is the frame ``START_M`` metres into the loop and its return
one loop later (``loops.find_revisit``); a KITTI cut therefore starts that far before its pose a.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import NamedTuple

import numpy as np

from gslam_jax.datasets.sim_path import world_kind
from gslam_jax.gridmap.grid import arc_length
from gslam_jax.sim.vonoise import VONoiseParams

START_M = 10.0  # the revisit's first frame: this far along the loop


def vo_noise(course: str, scale: float = 1.0, failures: float = 1.0) -> VONoiseParams:
    """The VO noise the loops of ``course`` are driven with: its profile (``world_kind``)
    with every std times ``scale`` (white noise and slow biases, ``VONoiseParams.scaled``) and
    the rate of VO-failure bursts (frames on wheel odometry, whose noise is the wheels')
    times ``failures`` (0: a VO that never fails)."""
    noise = world_kind(course)[1].scaled(scale)
    return dataclasses.replace(noise, failure_rate=noise.failure_rate * failures)


def add_vo_arguments(ap: argparse.ArgumentParser) -> None:
    """--vo-scale, --vo-failures and --noise-scale, the loop tools' VO and filter noise
    (``vo_noise``, ``experiments.common.scaled_alphas``), declared once for all of them."""
    ap.add_argument("--vo-scale", type=float, default=1.0,
                    help="the VO's noise (every std of the course's profile) times this")
    ap.add_argument("--vo-failures", type=float, default=1.0,
                    help="the rate of VO failures (wheel-odometry bursts) times this (0: none)")
    ap.add_argument("--noise-scale", type=float, default=1.0,
                    help="the filter's motion noise (the config's alphas) times this")


class Loop(NamedTuple):
    """A loop to drive: its name, kind ("circle" or "kitti"), nominal length and the
    trajectory file (TUM or KITTI) that drives it plus the overlap."""

    name: str
    kind: str
    length_m: float
    file: Path


def circle_loop(folder: Path, length: float, overlap: float) -> Loop:
    """The circle of perimeter ``length`` (``circle_file`` in ``folder``)."""
    return Loop(f"circle-{length:g}", "circle", length, circle_file(folder, length, overlap))


def kitti_loops(folder: Path, file: Path, lengths: list[float], radius: float,
                overlap: float) -> list[Loop]:
    """The cuts of a KITTI pose file nearest ``lengths`` (``kitti_cuts``), their files in
    ``folder``. The length is rounded to 0.1 m: it names the loop and sizes its map's margin,
    so every experiment driving the cut gets the same map."""
    return [Loop(f"kitti{file.stem}-{a}-{b}", "kitti", round(length, 1),
                 kitti_file(folder, file, a, b, overlap))
            for a, b, length in kitti_cuts(file, lengths, radius)]


def circle_file(folder: Path, length: float, overlap: float, step: float = 0.5) -> Path:
    """A TUM file of a circle of perimeter ``length`` driven once plus ``overlap`` metres."""
    r = length / (2 * np.pi)
    phi = np.arange(0.0, (length + overlap) / r + 1e-9, step / r)
    rows = [f"{0.1 * k:.3f} {r * np.sin(p):.6f} {r * (1 - np.cos(p)):.6f} 0 0 0 "
            f"{np.sin(p / 2):.9f} {np.cos(p / 2):.9f}" for k, p in enumerate(phi)]
    path = folder / f"circle-{length:g}.tum"
    path.write_text("\n".join(rows) + "\n")
    return path


def _kitti_xy(file: Path) -> np.ndarray:
    """Positions in the ground plane (camera x, z) of a KITTI pose file with times."""
    data = np.loadtxt(file, ndmin=2)
    m = data[:, -12:].reshape(-1, 3, 4)
    return np.stack([m[:, 0, 3], m[:, 2, 3]], axis=1)


def first_returns(xy: np.ndarray, radius: float) -> np.ndarray:
    """Per pose a of a path [N, 2]: the first later pose within ``radius`` of it after the path
    has left it by more than twice that (N where it never returns)."""
    n = len(xy)
    out = np.full(n, n)
    for a in range(n):
        d = np.hypot(*(xy[a:] - xy[a]).T)
        away = np.flatnonzero(d > 2 * radius)
        if away.size:
            back = np.flatnonzero(d[away[0]:] <= radius)
            if back.size:
                out[a] = a + away[0] + back[0]
    return out


def kitti_cuts(file: Path, lengths: list[float], radius: float, every: int = 5,
               lead_m: float = 20.0) -> list[tuple[int, int, float]]:
    """(a, b, loop length) per requested length, each loop once: the first return b of a pose
    a (``first_returns``), the pair whose loop is nearest the length; a runs over every
    ``every``-th pose. Only simple loops count: a cut is skipped where a pose inside it returns
    more than ``lead_m`` of travel before b (KITTI 08's 598 m loop holds its 478 m one, which
    the filter meets and closes first; returns just before b are the same revisit, met from
    the other side). A cut whose start and end both lie within ``lead_m`` of travel of an
    earlier one's is that loop again and is not given twice (KITTI 05's nearest 850 m and
    1000 m would be its 854 m loop from pose 1560 and its 855 m loop from pose 1555: one loop)."""
    xy = _kitti_xy(file)
    arc = arc_length(xy)
    back = first_returns(xy, radius)
    found = []
    for a in range(0, len(xy), every):
        b = int(back[a])
        if b < len(xy):
            inside = back[a:b]
            early = inside[inside < b]
            if early.size == 0 or arc[early.min()] >= arc[b] - lead_m:
                found.append((a, b, float(arc[b] - arc[a])))
    out: list[tuple[int, int, float]] = []
    for want in lengths:
        if not found:
            break
        cut = min(found, key=lambda f: abs(f[2] - want))
        if not any(abs(arc[cut[0]] - arc[a]) <= lead_m and abs(arc[cut[1]] - arc[b]) <= lead_m
                   for a, b, _ in out):  # two lengths nearest one loop drive it once
            out.append(cut)
    return out


def kitti_file(folder: Path, file: Path, a: int, b: int, overlap: float) -> Path:
    """The lines of a KITTI pose file from START_M metres before pose a (so that the revisit
    scored is a, b) to ``overlap`` metres after b."""
    lines = [ln for ln in file.read_text().splitlines() if ln.strip()]
    arc = arc_length(_kitti_xy(file))
    first = int(np.searchsorted(arc, arc[a] - START_M))
    end = int(np.searchsorted(arc, arc[b] + overlap))
    path = folder / f"{file.stem}-{a}-{b}.txt"
    path.write_text("\n".join(lines[first:end + 1]) + "\n")
    return path
