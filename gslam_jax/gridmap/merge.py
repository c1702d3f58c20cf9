"""Merging runs' maps into one frame (the paper's open problem of section 9).

Variance grid maps merge exactly: eq. 14 is a sum of sufficient statistics, so once run B's map
is placed in run A's frame (``align.align_maps``), the merged map is A's (k, S) plus B's, cell
by cell. N runs merge one after another, each aligned against the map merged so far, into the
frame of the first. Where both runs hold GPS alignments (``gps_alignment.npz`` of
``gslam run --gps``), their composition is a prior that narrows the search.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Callable, NamedTuple, Sequence

import numpy as np

from gslam_jax.gridmap.align import (AlignParams, Alignment, AlignmentRefused, PosePrior,
                                     align_maps)
from gslam_jax.gridmap.grid import (GridMap, MapFileError, add, compose, invert_pose, load_map,
                                    transform)

__all__ = ["MapRun", "Merged", "InconsistentMap", "SameMap", "check_distinct", "check_consistent",
           "consistency_problem", "load_run_folder", "gps_prior", "merge_maps", "merge_runs", "place_path"]


class MapRun(NamedTuple):
    """A finished run as merging sees it: a name, its map, its reported path (times [T],
    poses [T, 3]; None when the folder has none), when it was aligned to GPS, the pose of its
    map frame in the GPS site frame with the fit's residual RMS (metres), and its own run's
    check of the map against itself (``summary.json``'s ``map_consistency``, written by
    ``consistency``; None when not checked, and ``unchecked`` says why)."""

    name: str
    grid: GridMap
    times: np.ndarray | None = None
    path: np.ndarray | None = None
    gps_frame: np.ndarray | None = None
    gps_rms_m: float | None = None
    consistency: dict | None = None
    unchecked: str | None = None  # why its own run's self-check is not known (None: it is)


class InconsistentMap(AlignmentRefused):
    """A run's map failed its own run's consistency check (terrain mapped twice): merging it
    would carry the doubled terrain into the merge."""

    def __init__(self, message: str):
        super().__init__(message, None)


class SameMap(AlignmentRefused):
    """Two of the runs hold the same map (a run merged with itself, or a copy of it): the
    merge would count every cell's evidence twice."""

    def __init__(self, message: str):
        super().__init__(message, None)


class Merged(NamedTuple):
    """The merged map (in the first run's frame), each run's frame pose in it [3] (the first:
    zeros) and each later run's alignment (None for the first)."""

    grid: GridMap
    poses: list[np.ndarray]
    alignments: list[Alignment | None]


def load_run_folder(folder: str | Path) -> MapRun:
    """A ``gslam run`` results folder: map.npz, trajectory_tum.txt (if present) and the GPS
    frame from gps_alignment.npz with summary.json's residual, and summary.json's
    ``map_consistency`` (if present)."""
    from gslam_jax.io import read_tum

    folder = Path(folder)
    grid = load_map(folder)
    times = path = gps_frame = gps_rms = consistency = None
    unchecked = (f"{folder} is a bare map file, without its run's summary.json" if not
                 folder.is_dir() else None)
    if folder.is_dir():
        tum = folder / "trajectory_tum.txt"
        if tum.is_file():
            try:
                times, path = read_tum(tum)
            except (ValueError, IndexError) as err:
                raise MapFileError(f"{tum}: not a TUM trajectory ({err})") from err
        gps_file = folder / "gps_alignment.npz"
        if gps_file.is_file():
            with np.load(gps_file) as gps:
                R, shift = np.asarray(gps["R"], np.float64), np.asarray(gps["l"], np.float64)
                site = np.asarray(gps["site_origin"], np.float64)
            gps_frame = np.array([shift[0] + site[0], shift[1] + site[1],
                                  math.atan2(R[1, 0], R[0, 0])])
        summary_file = folder / "summary.json"
        if summary_file.is_file():
            try:
                summary = json.loads(summary_file.read_text())
            except ValueError as err:
                raise MapFileError(f"{summary_file}: not JSON ({err})") from err
            consistency = summary.get("map_consistency")
            if gps_frame is not None:
                gps_rms = summary.get("gps", {}).get("residual_rms_m")
            if consistency is None:
                unchecked = (f"{summary_file} records no map self-check (map_consistency; "
                             "its run was made with --no-map-check, or by an older version)")
        else:
            unchecked = f"{folder} has no summary.json"
        if unchecked is not None and not (folder / "COMPLETE").is_file():
            unchecked += " and no COMPLETE marker (not a finished gslam results folder)"
    return MapRun(folder.name, grid, times, path, gps_frame, gps_rms, consistency, unchecked)


def _same_grid(a: GridMap, b: GridMap) -> bool:
    """Whether two maps hold the same statistics on the same lattice."""
    return (a.k.shape == b.k.shape and a.resolution == b.resolution
            and float(a.heading) == float(b.heading)
            and np.array_equal(np.asarray(a.origin), np.asarray(b.origin))
            and np.array_equal(a.k, b.k) and np.array_equal(a.S, b.S))


def check_distinct(runs: Sequence[MapRun]) -> None:
    """Raise ``SameMap`` naming two runs whose maps are the same (the same folder twice, or a
    copy): eq. 14 would add the map to itself, doubling every cell's evidence."""
    for i, a in enumerate(runs):
        for b in runs[i + 1:]:
            if _same_grid(a.grid, b.grid):
                raise SameMap(f"{b.name} holds the same map as {a.name} (every cell's k and S, "
                              "the origin and the lattice equal): merging a run with itself "
                              "would double every cell's evidence; refused")


def gps_prior(a: MapRun, b: MapRun, min_std_m: float = 1.0) -> PosePrior | None:
    """The prior on B's frame in A's from both runs' GPS alignments (None unless both have
    one): mean A_gps^-1 (+) B_gps; position std the two residual RMS combined (at least
    ``min_std_m``, times 2 for the fits' own error), heading std that position error over
    B's map radius (at least 2 degrees)."""
    if a.gps_frame is None or b.gps_frame is None:
        return None
    rms = math.hypot(a.gps_rms_m or min_std_m, b.gps_rms_m or min_std_m)
    std_xy = max(2.0 * rms, min_std_m)
    centres = np.argwhere(b.grid.known) * b.grid.resolution + np.asarray(b.grid.origin)
    radius = max(float(np.max(np.linalg.norm(centres, axis=1))), 1.0)
    std_th = max(std_xy / radius, math.radians(2.0))
    return PosePrior(compose(invert_pose(a.gps_frame), b.gps_frame),
                     np.diag([std_xy ** 2, std_xy ** 2, std_th ** 2]))


def place_path(pose: np.ndarray, path: np.ndarray) -> np.ndarray:
    """Poses [T, 3] of a run's frame carried into the merged frame by the frame's ``pose``."""
    return np.stack([compose(pose, p) for p in np.asarray(path, np.float64)])


def merge_maps(grids: Sequence[GridMap], params: AlignParams = AlignParams(),
               priors: Sequence[PosePrior | None] | None = None,
               progress: Callable[[int, int], None] | None = None) -> Merged:
    """Merge maps into the frame of the first: each later map is aligned against the map merged
    so far (``align_maps``, which refuses a weak or ambiguous match with ``AlignmentRefused``)
    and its statistics added (eq. 14). ``priors[i]``: an optional prior on map i's frame in the
    first's."""
    if len(grids) < 2:
        raise ValueError(f"merging needs at least two maps, got {len(grids)}")
    merged = grids[0]
    poses: list[np.ndarray] = [np.zeros(3)]
    alignments: list[Alignment | None] = [None]
    for i, grid in enumerate(grids[1:], start=1):
        prior = priors[i] if priors is not None else None
        al = align_maps(merged, grid, params, prior=prior)
        merged = add(merged, transform(grid, al.pose, like=merged))
        poses.append(al.pose)
        alignments.append(al)
        if progress is not None:
            progress(i, len(grids) - 1)
    return Merged(merged, poses, alignments)


def consistency_problem(run: MapRun) -> str | None:
    """What ``run``'s own check found wrong with its map (terrain mapped twice), or None when
    it found nothing or did not check."""
    check = run.consistency
    if check is None or check.get("consistent", True):
        return None
    worst = max(check["doubled"], key=lambda r: r["offset_m"])
    return (f"{run.name}: its map is not consistent with itself (its run found "
            f"{len(check['doubled'])} of {check['revisits_checked']} revisited stretches fitting "
            f"its earlier map better elsewhere; worst: frames {worst['frames'][0]}-"
            f"{worst['frames'][1]}, {worst['offset_m']:.2f} m off): that terrain is mapped twice")


def check_consistent(run: MapRun) -> None:
    """Raise ``InconsistentMap`` when ``run``'s own check found its map doubled somewhere."""
    problem = consistency_problem(run)
    if problem is not None:
        raise InconsistentMap(f"{problem} and would be doubled in the merge; refused (allow it "
                              "with --allow-inconsistent)")


def merge_runs(runs: Sequence[MapRun], params: AlignParams = AlignParams(),
               use_gps: bool = True,
               progress: Callable[[int, int], None] | None = None,
               allow_inconsistent: bool = False) -> Merged:
    """``merge_maps`` over runs' maps, with GPS priors (``gps_prior`` against the first run)
    where both runs have a GPS alignment and ``use_gps``. A run whose map failed its own run's
    consistency check is refused (``InconsistentMap``) unless ``allow_inconsistent``; two runs
    with the same map always (``SameMap``)."""
    check_distinct(runs)
    if not allow_inconsistent:
        for run in runs:
            check_consistent(run)
    priors = [None] + [gps_prior(runs[0], r) if use_gps else None for r in runs[1:]]
    return merge_maps([r.grid for r in runs], params, priors, progress)
