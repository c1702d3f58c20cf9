"""Finished maps: reading, moving and summing them (eq. 14), aligning them by the gamma
likelihood (checked against a SciPy brute force) and merging them, on synthetic terrain whose
true placement is known."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest
from scipy.special import gammaln

from gslam_jax.errors import InputError
from gslam_jax.gridmap import (GridMap, MapFileError, add, compose, invert_pose, known_cells,
                               load_map, place, save_map, transform)
from gslam_jax.gridmap import align as align_mod
from gslam_jax.gridmap.align import AlignmentRefused, align_maps
from gslam_jax.gridmap.score import score_poses, temper
from gslam_jax.gridmap import merge as merge_mod
from gslam_jax.gridmap.align import AlignParams, PosePrior
from gslam_jax.gridmap.merge import merge_maps

RES = 0.16


def _roughness(x: np.ndarray, y: np.ndarray, seed: int) -> np.ndarray:
    """A terrain's height variance at world points: smooth ground with sensor noise plus
    scattered rocks (Gaussian bumps of variance), the same for every run of one seed."""
    rng = np.random.default_rng(seed)
    rocks = rng.uniform(-9, 9, (40, 2))
    size = rng.uniform(0.2, 0.6, 40)
    v = np.full(x.shape, 1e-3)
    for (cx, cy), s in zip(rocks, size):
        v += 0.05 * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s ** 2))
    return v


def _observe(world_seed: int, frame_pose: np.ndarray, half: float, noise_seed: int,
             k: int = 30) -> GridMap:
    """A map of the terrain in a frame whose pose in the world is ``frame_pose``: cells of a
    2 half x 2 half square (frame coordinates) with k dof and sample variance drawn around the
    terrain's variance at their centre."""
    n = int(2 * half / RES)
    origin = (-half, -half)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    local = np.column_stack([origin[0] + (i.ravel() + 0.5) * RES,
                             origin[1] + (j.ravel() + 0.5) * RES])
    c, s = math.cos(frame_pose[2]), math.sin(frame_pose[2])
    world = np.column_stack([frame_pose[0] + c * local[:, 0] - s * local[:, 1],
                             frame_pose[1] + s * local[:, 0] + c * local[:, 1]])
    v = _roughness(world[:, 0], world[:, 1], world_seed).reshape(n, n)
    rng = np.random.default_rng(noise_seed)
    S = v * rng.chisquare(k, (n, n))
    return GridMap(np.full((n, n), float(k)), S, origin, RES)


def _pose_error(est: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    return (math.hypot(est[0] - truth[0], est[1] - truth[1]),
            abs(math.degrees(math.remainder(est[2] - truth[2], 2 * math.pi))))


# --- GridMap values -----------------------------------------------------------------------

def test_load_map_names_file_and_field(tmp_path) -> None:
    with pytest.raises(MapFileError, match="no map.npz"):
        load_map(tmp_path)
    np.savez(tmp_path / "bad.npz", k=np.ones((2, 2)), S=np.ones((2, 2)))
    with pytest.raises(MapFileError, match=r"bad.npz: missing field\(s\) origin, resolution"):
        load_map(tmp_path / "bad.npz")
    np.savez(tmp_path / "neg.npz", k=np.ones((2, 2)), S=-np.ones((2, 2)), origin=[0.0, 0.0],
             resolution=0.1)
    with pytest.raises(MapFileError, match=r"neg.npz: 4 cells have invalid statistics"):
        load_map(tmp_path / "neg.npz")
    grid = GridMap(np.array([[0.0, 3.0]]), np.array([[0.0, 0.5]]), (1.0, 2.0), 0.2)
    save_map(tmp_path / "map.npz", grid)
    back = load_map(tmp_path)
    np.testing.assert_array_equal(back.k, grid.k)
    assert back.origin == grid.origin and back.resolution == pytest.approx(0.2)


def test_transform_moves_every_statistic_once() -> None:
    grid = _observe(1, np.zeros(3), 2.0, 0)
    pose = np.array([3.3, -1.7, 0.9])
    moved = transform(grid, pose)
    assert moved.k.sum() == pytest.approx(grid.k.sum())
    assert moved.S.sum() == pytest.approx(grid.S.sum())
    # each cell lands where its centre goes: spot-check against the pose by hand
    centres, k, S = known_cells(grid)
    c = centres[123]
    x = pose[0] + math.cos(pose[2]) * c[0] - math.sin(pose[2]) * c[1]
    y = pose[1] + math.sin(pose[2]) * c[0] + math.cos(pose[2]) * c[1]
    i = int(math.floor((x - moved.origin[0]) / RES))
    j = int(math.floor((y - moved.origin[1]) / RES))
    assert moved.k[i, j] >= k[123]


def test_add_is_eq14_over_the_union() -> None:
    a = GridMap(np.array([[1.0, 2.0]]), np.array([[0.1, 0.2]]), (0.0, 0.0), 0.5)
    b = GridMap(np.array([[4.0], [5.0]]), np.array([[0.4], [0.5]]), (0.0, 0.5), 0.5)
    s = add(a, b)
    assert s.origin == (0.0, 0.0) and s.shape == (2, 2)
    np.testing.assert_allclose(s.k, [[1.0, 6.0], [0.0, 5.0]])
    np.testing.assert_allclose(s.S, [[0.1, 0.6], [0.0, 0.5]])
    with pytest.raises(ValueError, match="not a whole number"):
        add(a, GridMap(b.k, b.S, (0.1, 0.5), 0.5))


def test_poses_compose_and_invert() -> None:
    a, b = np.array([1.0, 2.0, 0.7]), np.array([-0.5, 0.3, -2.0])
    np.testing.assert_allclose(compose(a, invert_pose(a)), 0.0, atol=1e-12)
    p = np.array([[0.4, -0.2]])
    from gslam_jax.gridmap import apply_pose
    np.testing.assert_allclose(apply_pose(compose(a, b), p), apply_pose(a, apply_pose(b, p)))


# --- the score against an independent brute force -----------------------------------------

def _log_predictive_scipy(kb, Sb, ka, Sa):
    k2, S2 = kb + ka, Sb + Sa
    return (gammaln(k2 / 2) - gammaln(kb / 2) - gammaln(ka / 2)
            + 0.5 * (kb * np.log(Sb) + ka * np.log(Sa) - k2 * np.log(S2)) - np.log(Sb / kb))


def test_score_matches_brute_force() -> None:
    """The score of a pose is sum over B's cells on A's known cells of lambda(b | a) minus its
    mean over A's known cells (eq. 26, tempered to max_dof), recomputed with SciPy."""
    a = _observe(3, np.zeros(3), 3.0, 1)
    truth = np.array([0.5, -0.3, 0.4])
    b = _observe(3, truth, 2.0, 2)
    pose = truth + np.array([0.05, 0.02, 0.01])
    score, z, overlap = score_poses(a, b, pose[None], max_dof=8)
    ka, Sa = temper(a.k, a.S, 8)
    kb, Sb = temper(b.k, b.S, 8)
    known_a = ka > 0
    centres, _, _ = known_cells(b)
    placed = np.column_stack([
        pose[0] + math.cos(pose[2]) * centres[:, 0] - math.sin(pose[2]) * centres[:, 1],
        pose[1] + math.sin(pose[2]) * centres[:, 0] + math.cos(pose[2]) * centres[:, 1]])
    i = np.floor((placed[:, 0] - a.origin[0]) / RES).astype(int)
    j = np.floor((placed[:, 1] - a.origin[1]) / RES).astype(int)
    inside = (i >= 0) & (i < a.shape[0]) & (j >= 0) & (j < a.shape[1])
    kbv, Sbv = kb[b.known], Sb[b.known]
    total, count = 0.0, 0
    for n in np.flatnonzero(inside):
        if not known_a[i[n], j[n]]:
            continue
        lam = _log_predictive_scipy(kbv[n], Sbv[n], ka[i[n], j[n]], Sa[i[n], j[n]])
        chance = _log_predictive_scipy(kbv[n], Sbv[n], ka[known_a], Sa[known_a]).mean()
        total += lam - chance
        count += 1
    assert overlap[0] == count
    scale = count * 0.05  # the chance mean is tabulated over log v: a small error per cell
    assert abs(score[0] - total) < scale, (score[0], total)
    assert z[0] > 5


def test_whole_cell_shift_search_equals_the_pose_scorer() -> None:
    """The coarse search's fast path (each heading indexed once, shifted by whole cells) gives
    the same scores as placing B at those poses one by one."""
    a = _observe(4, np.zeros(3), 2.5, 1)
    b = _observe(4, np.array([0.3, 0.1, 0.2]), 1.2, 2)
    params = align_mod.AlignParams(candidates=400, distinct_m=0.0, distinct_rad=0.0)
    poses, scores = align_mod._coarse_search(a, b, 2, params, None)
    again, _, _ = score_poses(a, b, poses, factor=2)
    np.testing.assert_allclose(again, scores, rtol=1e-4, atol=1e-2)


# --- alignment and merging on terrain with a known placement --------------------------------

TRUTH = np.array([1.3, -0.9, 2.4])  # B's frame in A's (the world is A's frame here)


class _Maps(NamedTuple):
    """Terrain 5 seen twice (A in the world frame, B from ``TRUTH``) and terrain 7 (C), each
    saved as a run folder and read back: the float32 maps ``gslam merge`` reads."""

    folder: Path
    a: GridMap
    b: GridMap
    c: GridMap


def _map_key(grid: GridMap) -> tuple:
    return (grid.k.tobytes(), grid.S.tobytes(), grid.k.shape,
            np.asarray(grid.origin, np.float64).tobytes(), float(grid.resolution),
            float(grid.heading))


class _AlignOnce:
    """``align_maps`` (or the search on the lattices' axes it runs, ``_align_lattices``, with
    the same arguments) remembered by its exact inputs (the maps' bytes and every setting): it
    is a pure function, so a second call with the same maps (``gslam merge`` on the folders of
    maps the API tests aligned) gets the same Alignment, or the same refusal, without the
    minute of search again. A call without ``refuse`` gets what the same call with it returned
    (an alignment that passed the checks is the one found without them). Any other input is
    aligned for real."""

    def __init__(self, align):
        self.align, self.seen = align, {}

    def __call__(self, a: GridMap, b: GridMap, params: AlignParams = AlignParams(),
                 prior: PosePrior | None = None, refuse: bool = True) -> align_mod.Alignment:
        key = (_map_key(a), _map_key(b), params, refuse, None if prior is None else
               (np.asarray(prior.mean).tobytes(), np.asarray(prior.cov).tobytes()))
        strict = key[:3] + (True,) + key[4:]
        if key not in self.seen and strict in self.seen and self.seen[strict][1] is None:
            # not refused with ``refuse``: the checks passed, and without them the same
            # search returns the same Alignment
            self.seen[key] = self.seen[strict]
        if key not in self.seen:
            try:
                self.seen[key] = (self.align(a, b, params, prior=prior, refuse=refuse), None)
            except AlignmentRefused as err:
                self.seen[key] = (None, (str(err), err.alignment))
        result, refused = self.seen[key]
        if refused is not None:
            raise AlignmentRefused(*refused)
        return result


@pytest.fixture(scope="module")
def maps(tmp_path_factory) -> _Maps:
    folder = tmp_path_factory.mktemp("runs")
    grids = {}
    # A 9 x 9 m: its reverse search (A onto B, the mutual check) then starts at 4 x 4 cells,
    # where 8 x 8 m was just inside the budget at 2 x 2 and cost ten times as much. C 22 x 22
    # cells (its 2 x 2 blocks fit one bucket of 128): half the search of B's size, refused for
    # the same reason (ambiguous, best z 15.6 above min_z)
    for name, grid in (("a", _observe(5, np.zeros(3), 4.5, 1)), ("b", _observe(5, TRUTH, 2.5, 2)),
                       ("c", _observe(7, np.zeros(3), 1.8, 3))):
        (folder / name).mkdir()
        save_map(folder / name / "map.npz", grid)
        grids[name] = load_map(folder / name)
    return _Maps(folder, **grids)


@pytest.fixture(scope="module")
def align(maps):
    """The alignment every test of this section makes, merge_maps and ``gslam merge`` included
    (``_AlignOnce``): each pair of maps is searched once per module. The search on the
    lattices' axes is remembered too: maps on turned lattices are searched as the same maps
    on their axes, so their search, and the reverse one of their mutual check, is the unturned
    pair's."""
    once = _AlignOnce(merge_mod.align_maps)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(merge_mod, "align_maps", once)
        mp.setattr(align_mod, "_align_lattices", _AlignOnce(align_mod._align_lattices))
        yield once

def test_align_refuses_unrelated_or_featureless_maps(maps, align) -> None:
    a, other = maps.a, maps.c  # another terrain
    with pytest.raises(AlignmentRefused, match="cannot align the maps") as err:
        align(a, other)
    assert err.value.alignment.overlap > 0
    # B 16 x 16 cells: more than min_overlap (200), half the search of 20 x 20
    flat = GridMap(np.full((40, 40), 30.0), np.full((40, 40), 0.03), (0.0, 0.0), RES)
    with pytest.raises(AlignmentRefused):
        align_maps(flat, GridMap(flat.k[:16, :16], flat.S[:16, :16], (0.0, 0.0), RES))
    with pytest.raises(InputError, match="different resolutions"):
        align_maps(a, GridMap(other.k, other.S, other.origin, 0.2))


def test_merge_recovers_an_unknown_placement_and_sums_the_statistics(maps, align) -> None:
    a, b, truth = maps.a, maps.b, TRUTH
    merged = merge_maps([a, b])
    al = merged.alignments[1]
    dist, deg = _pose_error(al.pose, truth)
    assert dist < 0.5 * RES and deg < 0.5, (al.pose, truth)
    std = np.sqrt(np.diag(al.covariance))
    assert np.all(std[:2] < 0.1) and not al.runner_up_z >= al.z  # NaN: no distinct peak
    assert merged.grid.k.sum() == pytest.approx(a.k.sum() + b.k.sum())
    assert merged.grid.S.sum() == pytest.approx(a.S.sum() + b.S.sum())
    np.testing.assert_allclose(merged.poses[1], merged.alignments[1].pose)
    # B's rocks (cells of variance > 0.01 m^2) now lie on A's rocks, and do not when B is
    # placed 3 m off
    def agreement(pose):
        placed = transform(b, pose, like=a)
        union = add(a, placed)
        pa = place(a, union.origin, union.shape)
        pb = place(placed, union.origin, union.shape)
        both = (pa.k > 0) & (pb.k > 0)
        rock_a = pa.S[both] / pa.k[both] > 0.01
        rock_b = pb.S[both] / pb.k[both] > 0.01
        return np.sum(rock_a & rock_b) / np.sum(rock_a | rock_b)

    good = agreement(merged.poses[1])
    assert good > 0.6
    assert agreement(merged.poses[1] + np.array([3.0, 0.0, 0.0])) < 0.5 * good


def test_maps_on_turned_lattices_align_and_merge_in_their_frames(maps, align,
                                                                  tmp_path) -> None:
    """A and B with their lattices turned in their frames (``GridMap.heading``, a map of
    ``[map] axes = "start"``): the alignment is found on the lattices' axes and carried into
    the frames, where B's frame now lies at Ha (+) TRUTH (+) Hb^-1; the merge sums every
    statistic onto A's turned lattice."""
    ha, hb = 0.5, -0.9
    a, b = maps.a._replace(heading=ha), maps.b._replace(heading=hb)
    truth = compose(compose(np.array([0.0, 0.0, ha]), TRUTH), np.array([0.0, 0.0, -hb]))
    merged = merge_maps([a, b])
    al, plain = merged.alignments[1], align(maps.a, maps.b)
    dist, deg = _pose_error(al.pose, truth)
    assert dist < 0.5 * RES and deg < 0.5, (al.pose, truth)
    # the same search as on the frames' axes, turned: the covariance too
    J = np.eye(3)
    J[:2, :2] = [[math.cos(ha), -math.sin(ha)], [math.sin(ha), math.cos(ha)]]
    np.testing.assert_allclose(al.covariance, J @ plain.covariance @ J.T, rtol=1e-6, atol=1e-12)
    assert merged.grid.heading == ha
    assert merged.grid.k.sum() == pytest.approx(a.k.sum() + b.k.sum())
    # gslam merge on run folders of these maps: the merge keeps A's turned lattice
    from gslam_jax.app.cli import main

    for name, grid in (("a", a), ("b", b)):
        (tmp_path / name).mkdir()
        save_map(tmp_path / name / "map.npz", grid)
    out = tmp_path / "merged"
    assert main(["merge", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(out)]) == 0
    pose = np.array(json.loads((out / "summary.json").read_text())["runs"][1]
                    ["pose_in_merged_frame"])
    assert _pose_error(pose, truth)[0] < 0.5 * RES
    assert load_map(out).heading == pytest.approx(ha) and (out / "map.png").is_file()


def test_gslam_merge_writes_the_merge_or_refuses_it(maps, align, tmp_path, capsys) -> None:
    from gslam_jax.app.cli import main

    runs = maps.folder
    out = tmp_path / "merged"
    assert main(["merge", str(runs / "a"), str(runs / "b"), "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    pose = np.array(summary["runs"][1]["pose_in_merged_frame"])
    assert _pose_error(pose, TRUTH)[0] < 0.5 * RES
    assert (out / "map.png").is_file() and load_map(out).known.sum() > 0
    refused = tmp_path / "refused"
    assert main(["merge", str(runs / "a"), str(runs / "c"), "--out", str(refused)]) == 2
    assert "cannot align the maps" in capsys.readouterr().err
    assert not refused.exists()


def test_merge_refuses_a_map_its_own_run_found_doubled(maps, align, tmp_path, capsys) -> None:
    """A run folder whose summary.json records a failed self-check (``map_consistency``) is
    refused before any alignment, naming the run and the stretch; --allow-inconsistent merges
    it as the check-free folder would be."""
    import shutil

    from gslam_jax.app.cli import main

    doubled = tmp_path / "b-doubled"
    shutil.copytree(maps.folder / "b", doubled)
    check = {"consistent": False, "revisits_checked": 5, "worst_offset_m": 2.4,
             "doubled": [{"frames": [310, 352], "offset_m": 2.4, "z_best": 30.0,
                          "z_as_mapped": 2.0}]}
    (doubled / "summary.json").write_text(json.dumps({"map_consistency": check}))
    run = merge_mod.load_run_folder(doubled)
    assert run.consistency == check
    with pytest.raises(merge_mod.InconsistentMap, match=r"b-doubled: .*frames 310-352, 2\.40 m"):
        merge_mod.merge_runs([merge_mod.load_run_folder(maps.folder / "a"), run])
    out = tmp_path / "refused"
    assert main(["merge", str(maps.folder / "a"), str(doubled), "--out", str(out)]) == 2
    assert "not consistent with itself" in capsys.readouterr().err and not out.exists()
    out = tmp_path / "allowed"
    assert main(["merge", str(maps.folder / "a"), str(doubled), "--out", str(out),
                 "--allow-inconsistent"]) == 0
    pose = np.array(json.loads((out / "summary.json").read_text())["runs"][1]
                    ["pose_in_merged_frame"])
    assert _pose_error(pose, TRUTH)[0] < 0.5 * RES
    # a consistent check does not stand in the way
    (doubled / "summary.json").write_text(json.dumps({"map_consistency": {
        "consistent": True, "revisits_checked": 5, "doubled": [], "worst_offset_m": 0.0}}))
    merge_mod.check_consistent(merge_mod.load_run_folder(doubled))


def test_merge_refuses_a_run_merged_with_itself(maps, tmp_path, capsys) -> None:
    """``gslam merge A A``, or A and a copy of it under another name, would add A's map to
    itself (every cell's evidence doubled): refused before any alignment or folder, naming both;
    the API refuses it too."""
    import shutil

    from gslam_jax.app.cli import main

    copy = tmp_path / "a-copy"
    shutil.copytree(maps.folder / "a", copy)
    for second in (maps.folder / "a", copy, copy / "map.npz"):
        out = tmp_path / "refused"
        assert main(["merge", str(maps.folder / "a"), str(second), "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert f"{second.name} holds the same map as a" in err and "double" in err, err
        assert not out.exists()
    with pytest.raises(merge_mod.SameMap):
        merge_mod.merge_runs([merge_mod.load_run_folder(maps.folder / "a"),
                              merge_mod.load_run_folder(copy)])


def test_merge_says_which_runs_it_cannot_self_check(maps, tmp_path) -> None:
    """A bare map.npz, a folder without summary.json (or without COMPLETE) and a summary without
    map_consistency each carry the reason their self-check is unknown (printed by gslam merge);
    a complete folder whose summary holds the check carries none."""
    import shutil

    bare = merge_mod.load_run_folder(maps.folder / "a" / "map.npz")
    assert "bare map file" in bare.unchecked
    folder = merge_mod.load_run_folder(maps.folder / "a")
    assert "has no summary.json" in folder.unchecked and "no COMPLETE" in folder.unchecked
    done = tmp_path / "done"
    shutil.copytree(maps.folder / "a", done)
    (done / "summary.json").write_text(json.dumps({"distance_m": 1.0}))
    (done / "COMPLETE").write_text("{}")
    assert "records no map self-check" in merge_mod.load_run_folder(done).unchecked
    (done / "summary.json").write_text(json.dumps({"map_consistency": {
        "consistent": True, "revisits_checked": 2, "doubled": [], "worst_offset_m": 0.0}}))
    assert merge_mod.load_run_folder(done).unchecked is None


def test_gslam_merge_prints_the_skipped_self_checks(maps, align, tmp_path, capsys) -> None:
    from gslam_jax.app.cli import main

    out = tmp_path / "merged"
    assert main(["merge", str(maps.folder / "a"), str(maps.folder / "b" / "map.npz"),
                 "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "note: a: " in err and "note: map.npz: " in err and "check is skipped" in err
