"""Map merging on the simulator, whose truth is known: align run B's finished map to run A's
(``gridmap.align_maps``, the gamma likelihood) from an unknown start, against the paper's
GPS-only alignment, and refuse pairs of different courses.

    python -m experiments.map_merge --courses mars-yard-a arroyo-a maze --trials 10 \
        --json map_merge.json

Per course: run A is the course with sim seed 0; trial i drives the same world and path again
with other VO and sensor noise (``--noise-seed 100 + i``) and starts B's frame at a random pose
Q (offset uniform up to the course's size, any heading), so B's map lives in an unknown frame;
the true pose of B's frame in A's is then T = g0 (+) Q^-1 (g0: the true start, A's start pose).
Both maps carry their own SLAM errors, so a second reference is the pose that best lays the
path of B's map on A's frame by frame (they drive the same true poses): the best any rigid
alignment of these two maps can do. Each map is one particle's (``rbpf.map_particle``), so
the path is that particle's (``SlamResult.map_path``), not the reported one (``[filter]
estimate``, by default the mean steps over every particle), which can lie half a metre from
it where the weights are flat. Each trial reports the alignment's error against both,
its standard deviation, z and runner-up, whether ``align_maps`` would refuse it, and the
error of the GPS-only alignment (each run's path aligned to its own simulated WAAS-like
receiver, paper appendix, then composed); with ``--self-check``, whether B's map passes its
own run's check against itself (``consistency``; ``gslam merge`` refuses it when not).
Then A of each course is aligned to B of the next
course (no overlap), ``--cross`` pairs in all: each should be refused. Every run takes the
defaults, or ``--config`` (with its tables for each course: ``configs/table1.toml`` gives each
course its calibrated noise) and ``--set``. B's frame is turned at random; on the robot's start
axes (the default) every run's map lattice lies on them, while on the frame's (``--set
map.axes=frame``, which ``configs/table1.toml`` pins) B's lies at a random angle to the
terrain (on the maze that breaks B's maps, docs/notebook/results.md).
"""

from __future__ import annotations

import argparse
import json
import math
import tomllib
import time
from pathlib import Path

import numpy as np

from gslam_jax.config import Config, config_to_toml, layered_config, parse_config
from gslam_jax.sim.courses import COURSES
from gslam_jax.datasets.sim import simulate_run
from gslam_jax.driver import slam
from gslam_jax.driver.machine import environment
from gslam_jax.driver.results import SlamResult
from gslam_jax.evaluation.metrics import rigid_fit_2d
from gslam_jax.gps import align_to_gps
from gslam_jax.gps.georeference import gps_input
from gslam_jax.gridmap import GridMap, add, compose, invert_pose, transform
from gslam_jax.gridmap.align import AlignmentRefused, align_maps, check_alignment
from gslam_jax.vo.localmap import localmap_params


def _slam_map(run, config: Config) -> tuple[GridMap, SlamResult]:
    result = slam.run_slam(run, config)
    return result.grid, result


def _gps_frame(run, result, seed: int) -> np.ndarray:
    """The pose of the run's map frame in the GPS site frame (Procrustes fit of its path)."""
    readings = gps_input("sim", run, seed)
    al, _ = align_to_gps(run.timestamps, result.path[:, :2], readings.log.time,
                         readings.log.xy, readings.log.epe)
    R, shift = np.asarray(al.R, np.float64), np.asarray(al.l, np.float64)
    return np.array([shift[0], shift[1], math.atan2(R[1, 0], R[0, 0])])


def _path_fit(path_a: np.ndarray, path_b: np.ndarray) -> np.ndarray:
    """The pose of B's frame in A's that best lays B's estimated path on A's, frame by frame
    (both drive the same true poses): ``metrics.rigid_fit_2d`` of the positions."""
    fit = rigid_fit_2d(path_b, path_a)
    return np.array([fit.translation[0], fit.translation[1], fit.angle])


def _map_path(run: dict, cache: Path | None, name: str) -> np.ndarray:
    """The path of a run's map (its best particle's); a cache made before it was kept is
    named."""
    if "map_path" not in run:
        raise SystemExit(f"{cache}/{name}.npz: made before the map's own path was kept; "
                         "give a new --cache")
    return run["map_path"]


def _cell_error(grid_b: GridMap, est: np.ndarray, truth: np.ndarray) -> float:
    """RMS distance between B's known cells placed by ``est`` and by ``truth``: the error as
    the merge sees it (the frame origin's error alone grows with its distance from the map)."""
    from gslam_jax.gridmap import apply_pose, known_cells

    centres, _, _ = known_cells(grid_b)
    d = apply_pose(est, centres) - apply_pose(truth, centres)
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def _figure(out: Path, grid_a: GridMap, grid_b: GridMap, pose: np.ndarray, merged: GridMap,
            course: str) -> None:
    from gslam_jax.app.plots import save_maps_png

    out.parent.mkdir(parents=True, exist_ok=True)
    placed = transform(grid_b, pose, like=grid_a)
    save_maps_png(out, [(title, g.expected_std(), (*g.origin, g.heading), None)
                        for title, g in ((f"A ({course})", grid_a),
                                         ("B placed by the alignment", placed),
                                         ("merged", merged))],
                  grid_a.resolution)


def _error(est: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    return (float(math.hypot(est[0] - truth[0], est[1] - truth[1])),
            float(abs(math.degrees(math.remainder(est[2] - truth[2], 2 * math.pi)))))


def _cached(cache: Path | None, name: str, config: Config, make) -> dict:
    """``make()`` (a dict of arrays), kept as ``cache/name.npz`` when a cache folder is given,
    with the config it was made with; a cached run of another config is an error."""
    if cache is None:
        return make()
    file = cache / f"{name}.npz"
    toml = config_to_toml(config)
    if not file.exists():
        cache.mkdir(parents=True, exist_ok=True)
        np.savez(file, config_toml=np.array(toml), **make())
    with np.load(file) as data:
        made_with = str(data["config_toml"]) if "config_toml" in data.files else None
        # compared as configs, not as text: a setting added since, at its default, is the same
        if made_with is not None and parse_config(tomllib.loads(made_with), str(file)) != config:
            raise SystemExit(f"{file}: cached with another config; give this config its own "
                             "--cache")
        return {k: data[k] for k in data.files if k != "config_toml"}


def _run_maps(course: str, noise_seed: int | None, start: np.ndarray | None, config: Config,
              gps_seed: int) -> dict:
    """Run the course (sim seed 0; B: another noise seed and start pose ``start``): its map,
    true start, extent and the pose of its map frame in the GPS site frame."""
    run, info = simulate_run(course, seed=0, params=localmap_params(config),
                             noise_seed=noise_seed)
    if start is not None:
        run = run._replace(initial_pose=start)
    grid, result = _slam_map(run, config)
    g0 = np.asarray(run.ground_truth[0], np.float64)
    return {"k": grid.k, "S": grid.S, "origin": np.asarray(grid.origin),
            "resolution": grid.resolution, "heading": grid.heading, "g0": g0, "path": result.path,
            "map_path": result.map_path,
            "size": np.max(np.abs(run.ground_truth[:, :2] - g0[:2])),
            "gps_frame": _gps_frame(run, result, gps_seed),
            **({} if start is not None else {
                "world_height": info.world.height, "world_rough": info.world.rough,
                "world_origin": np.asarray(info.world.origin),
                "world_resolution": info.world.resolution})}


def _self_check(course: str, trial: int, path: np.ndarray, config: Config) -> dict:
    """Trial ``trial``'s B map checked against itself at its own path (the Run simulated again:
    the local maps do not depend on the start pose), as ``gslam run`` checks it; a doubled map
    is refused as ``gslam merge`` refuses it."""
    from gslam_jax.gridmap.consistency import check_consistency

    run, _ = simulate_run(course, seed=0, params=localmap_params(config),
                          noise_seed=100 + trial)
    check = check_consistency(run, path)
    return {"self_consistent": check.consistent, "self_revisits": len(check.revisits),
            "self_doubled": len(check.doubled),
            "self_worst_offset_m": max((r.offset_m for r in check.doubled), default=0.0),
            "merge_refused": not check.consistent}


def _true_std(a: dict, grid: GridMap) -> np.ndarray:
    """The simulated world's true spread of heights in each cell of ``grid`` (a map in the
    world frame, its lattice turned by its heading): the spread of the world's pixel heights
    in the cell with each pixel's own return spread (``World.rough``) added in quadrature; NaN
    where no pixel falls."""
    h, rough = a["world_height"], a["world_rough"]
    res_w = float(a["world_resolution"])
    i, j = np.meshgrid(np.arange(h.shape[0]), np.arange(h.shape[1]), indexing="ij")
    x = a["world_origin"][0] + (i + 0.5) * res_w
    y = a["world_origin"][1] + (j + 0.5) * res_w
    c, s = math.cos(grid.heading), math.sin(grid.heading)
    x, y = c * x + s * y, -s * x + c * y  # onto the lattice's axes
    ci = np.floor((x - grid.origin[0]) / grid.resolution).astype(np.int64).ravel()
    cj = np.floor((y - grid.origin[1]) / grid.resolution).astype(np.int64).ravel()
    inside = (ci >= 0) & (ci < grid.shape[0]) & (cj >= 0) & (cj < grid.shape[1])
    flat = (ci * grid.shape[1] + cj)[inside]
    hv, rv = h.ravel()[inside].astype(np.float64), rough.ravel()[inside].astype(np.float64)
    size = grid.shape[0] * grid.shape[1]
    n = np.bincount(flat, minlength=size)
    s1 = np.bincount(flat, hv, minlength=size)
    s2 = np.bincount(flat, hv * hv, minlength=size)
    r2 = np.bincount(flat, rv * rv, minlength=size)
    with np.errstate(invalid="ignore", divide="ignore"):
        var = s2 / n - (s1 / n) ** 2 + r2 / n
    return np.sqrt(np.clip(var, 0.0, None)).reshape(grid.shape)


def _roughness_corr(a: dict, grid: GridMap) -> float:
    """Correlation of log expected std with log true spread over the map's known cells: an
    obstacle doubled by a misplaced merge blurs it."""
    truth = _true_std(a, grid)
    std = grid.expected_std()
    ok = np.isfinite(std) & np.isfinite(truth) & (truth > 0) & (std > 0)
    return float(np.corrcoef(np.log(std[ok]), np.log(truth[ok]))[0, 1])


def _grid(d: dict) -> GridMap:
    return GridMap(d["k"], d["S"], tuple(d["origin"]), float(d["resolution"]),
                   float(d.get("heading", 0.0)))


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--courses", nargs="+", default=["mars-yard-a", "arroyo-a", "maze"])
    ap.add_argument("--trials", type=int, default=10)
    ap.add_argument("--json", default=None)
    ap.add_argument("--cache", default=None, help="keep each run's map here (re-runs skip SLAM)")
    ap.add_argument("--maps-only", action="store_true", help="only run SLAM and fill --cache")
    ap.add_argument("--cross-only", action="store_true",
                    help="only align pairs of different courses (the trials' maps from --cache)")
    ap.add_argument("--figures", default=None, help="write A, B placed and the merge of each "
                    "course's first trial here")
    ap.add_argument("--self-check", action="store_true",
                    help="also check each B's map against itself (consistency, as gslam "
                         "run does); a doubled map is refused as gslam merge refuses it")
    ap.add_argument("--cross", type=int, default=10,
                    help="pairs of different courses to align (each should be refused)")
    ap.add_argument("--config", type=Path, default=None,
                    help="TOML config of every run (default: the defaults); a Table I config's "
                         "tables for each course apply (configs/table1.toml: its calibrated "
                         "noise); a --cache holds the runs of one config")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="override one config value (repeatable)")
    args = ap.parse_args(argv)
    report = {"environment": environment(), "config": str(args.config), "set": args.set,
              "trials": [], "cross": []}
    maps = {}
    cache = Path(args.cache) if args.cache else None
    for course in args.courses:
        config = layered_config(args.config, course, args.set, courses=COURSES)
        a = _cached(cache, f"{course}-a", config,
                    lambda: _run_maps(course, None, None, config, 1000))
        g0, size = a["g0"], float(a["size"])
        maps[course] = {"a": _grid(a), "b": []}
        for i in range(args.trials):
            rng = np.random.default_rng([7, i])
            Q = np.array([rng.uniform(-size, size), rng.uniform(-size, size),
                          rng.uniform(-math.pi, math.pi)])
            b = _cached(cache, f"{course}-b{i}", config,
                        lambda: _run_maps(course, 100 + i, Q, config, 2000 + i))
            truth = compose(g0, invert_pose(Q))
            grid_b = _grid(b)
            maps[course]["b"].append(grid_b)
            if args.maps_only or args.cross_only:
                continue
            t0 = time.perf_counter()
            al = align_maps(maps[course]["a"], grid_b, refuse=False)
            seconds = time.perf_counter() - t0
            try:
                check_alignment(al)
                refused = None
            except AlignmentRefused as err:
                refused = str(err)
            merged = add(maps[course]["a"], transform(grid_b, al.pose, like=maps[course]["a"]))
            placed_true = transform(grid_b, truth, like=maps[course]["a"])
            corr = {"corr_a": _roughness_corr(a, maps[course]["a"]),
                    "corr_b_placed_true": _roughness_corr(a, placed_true),
                    "corr_merged": _roughness_corr(a, merged)}
            gps = compose(invert_pose(a["gps_frame"]), b["gps_frame"])
            fit = _path_fit(_map_path(a, cache, f"{course}-a"),
                            _map_path(b, cache, f"{course}-b{i}"))
            fdist, fhead = _error(al.pose, fit)
            dist, head = _error(al.pose, truth)
            gdist, ghead = _error(gps, truth)
            std = np.sqrt(np.diag(al.covariance))
            row = {"course": course, "trial": i, "error_m": dist, "error_deg": head,
                   "cells_error_m": _cell_error(grid_b, al.pose, truth),
                   "path_fit_error_m": fdist, "path_fit_error_deg": fhead,
                   "path_fit_cells_error_m": _cell_error(grid_b, al.pose, fit),
                   "gps_cells_error_m": _cell_error(grid_b, gps, truth),
                   "std_m": float(math.hypot(std[0], std[1])),
                   "std_deg": math.degrees(float(std[2])), "z": al.z,
                   "runner_up_z": al.runner_up_z, "overlap": al.overlap, "refused": refused,
                   "cycle_m": al.cycle_m, "cycle_deg": math.degrees(al.cycle_rad),
                   "gps_error_m": gdist, "gps_error_deg": ghead, "seconds": seconds, **corr}
            if args.self_check:
                row.update(_self_check(course, i, b["path"], config))
            report["trials"].append(row)
            print(json.dumps(row), flush=True)
            if args.figures and i == 0:
                _figure(Path(args.figures) / f"merge-{course}.png", maps[course]["a"], grid_b,
                        al.pose, merged, course)
    courses = list(maps)
    for i in range(0 if args.maps_only else args.cross):
        course = courses[i % len(courses)]
        other = courses[(i + 1) % len(courses)]
        if other == course:
            break
        grid_b = maps[other]["b"][(i // len(courses)) % args.trials]
        al = align_maps(maps[course]["a"], grid_b, refuse=False)
        try:
            check_alignment(al)
            refused = None
        except AlignmentRefused as err:
            refused = str(err)
        row = {"a": course, "b": other, "pair": i, "z": al.z, "runner_up_z": al.runner_up_z,
               "overlap": al.overlap, "refused": refused}
        report["cross"].append(row)
        print(json.dumps(row), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2))
    return report


if __name__ == "__main__":
    main()
