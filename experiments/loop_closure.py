"""How long a loop the filter closes: closure probability against loop length, per proposal and
number of particles J (the paper's section 9 question).

    python -m experiments.loop_closure --circles 50 100 200 400 \
        --kitti ../shared/data/kitti-poses/00.txt --kitti-lengths 300 600 \
        --particles 20 200 --seeds 0 1 2 3 4 --json loops.json --plot loops.png
    # a big machine: --particles 2000 20000 --store shared

Loops: circles of the given perimeters, and cuts of KITTI pose files: the first return of a pose
j to within --radius of an earlier pose i, with the travel between them nearest each
--kitti-lengths value, among the simple loops (none that holds a shorter loop the filter would
meet and close first: ``loop_paths.kitti_cuts``). Each loop is driven once and then --overlap
metres on, through a corridor world of --course (``datasets.sim_path``); seed s is both the
simulation seed (world and VO noise) and the filter seed. The revisit scored is the frame at 10
m of travel and its return one loop later; the verdict is ``evaluation.loops.closure`` (revisit
error and map offset <= 1 m) of the final best particle's path, of the final densest particle's
path (``[filter] estimate = "mode"``: after a revisit's resampling the weights are nearly equal,
and the best particle can be one of the few that missed the start while most of the weight is
near the truth; ``--verdict mode`` summarises by it), of the smoother's mean over the final
particles within 1 m of that one (``"mode_mean"``, that component's posterior mean; ``--verdict
mode_mean``) and of the VO-only path.
--vo-scale F drives the loops with every std of the course's VO noise times F (a better or
worse VO), --vo-failures F with its failures' rate times F (0: a VO that never fails), and
--noise-scale F multiplies the filter's alphas, as in ``experiments.loop_bound``.

Each run also records the cloud just before the sensor can first see the start's map
(``approach_*``: the particle nearest the truth, and how many are within 1, 2, 3 and 5 m of
it): where none is within the closure's 1 m, no weighting at the revisit can close the loop,
and more particles are what it needs. The summary splits each (proposal, J)'s closures by
that cloud.

Each row holds its filter and wall seconds and the process's peak RSS so far (``peak_rss_mib``:
that run's own where a process runs one seed at one J, as the kilometre runs are made).
Prints one line per run, then per (proposal, J) the closure rate at each length and the
longest loop closed in >= 80 % of the seeds; with --progress also a line on stderr per chunk of
frames filtered (runs at J = 2000 and more take hours on a small machine). Runs made apart (a
seed per process, J = 2000 on another machine) are summarised and plotted together with
--from-json A.json B.json ... --plot loops.png, which runs nothing; --resume keeps the runs
already in --json and runs the rest (after an interruption, or to add seeds).
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import tempfile
import time
from pathlib import Path
from typing import Collection

import numpy as np

from experiments.common import scaled_alphas
from experiments.loop_paths import (START_M, Loop, add_vo_arguments, circle_loop, kitti_loops,
                                   vo_noise)
from experiments.loop_summary import VERDICTS, plot, print_summary, read_rows
from gslam_jax.config import apply_overrides, layered_config
from gslam_jax.sim.courses import COURSES
from gslam_jax.datasets.sim_path import simulate_path
from gslam_jax.driver import slam
from gslam_jax.driver.machine import environment
from gslam_jax.driver.results import ChunkReport
from gslam_jax.evaluation import loops, metrics
from gslam_jax.gridmap.grid import arc_length
from gslam_jax.vo.localmap import localmap_params

APPROACH_M = 2.0  # the cloud is read this far before the sensor first reaches the start's map


def score(run, res, revisit: loops.Revisit) -> dict:
    """The closure figures of one filter run: its best particle's path, the path of its final
    densest particle (``[filter] estimate = "mode"``, ``mode_*``), the smoother's mean over
    that particle's 1 m neighbourhood (``"mode_mean"``, ``mode_mean_*``) and the VO path."""
    slam_c = loops.closure(run, res.best_path, revisit)
    mode_c = loops.closure(run, res.mode_path, revisit)
    mean_c = loops.closure(run, res.mode_mean_path, revisit)
    vo_c = loops.closure(run, res.vo_path, revisit)
    return {"closed": slam_c.closed, "error_m": slam_c.error_m,
            "map_offset_m": slam_c.map_offset_m, "map_corr": slam_c.map_corr,
            "mode_closed": mode_c.closed, "mode_error_m": mode_c.error_m,
            "mode_map_offset_m": mode_c.map_offset_m,
            "mode_mean_closed": mean_c.closed, "mode_mean_error_m": mean_c.error_m,
            "mode_mean_map_offset_m": mean_c.map_offset_m,
            "smoothed_error_m": loops.revisit_error(run.ground_truth, res.smoothed_path,
                                                    revisit.i, revisit.j),
            "vo_closed": vo_c.closed, "vo_error_m": vo_c.error_m,
            "vo_map_offset_m": vo_c.map_offset_m,
            "slam_rms_m": metrics.rms_after_fit(res.best_path, run.ground_truth),
            "vo_rms_m": metrics.rms_after_fit(res.vo_path, run.ground_truth)}


def approach_frame(truth: np.ndarray, revisit: loops.Revisit, reach_m: float) -> int:
    """The last frame at least ``APPROACH_M`` metres of travel before the sensor (range
    ``reach_m``) can first see the map made at the loop's start: the particles there have met
    nothing but their own maps since, so how near the truth they are is the sample's doing
    alone."""
    arc = arc_length(truth)
    at = arc[revisit.j] - (reach_m + APPROACH_M + START_M)
    return int(np.clip(np.searchsorted(arc, at, side="right") - 1, 0, revisit.j))


APPROACH_RADII = (1, 2, 3, 5)  # m: particles are counted within each of the truth


class ApproachCloud:
    """An ``on_chunk`` callback that keeps how near the particles came to the truth at one
    frame: ``nearest_m`` and ``within`` (particles within each of ``APPROACH_RADII`` metres;
    1 m is the closure's tolerance, the wider ones tell its density where none is that near),
    and ``nearest_heading_deg``, the heading error of the particle nearest in position (a
    near particle turned a few degrees scores worse on the old map than the far ones as it
    drives on: docs/notebook/results.md, KITTI 00)."""

    def __init__(self, frame: int):
        self.frame, self.nearest_m, self.within = frame, None, {}
        self.nearest_heading_deg = None

    def __call__(self, report: ChunkReport) -> None:
        t = self.frame - report.start
        if 0 <= t < len(report.best_pose):
            pose = np.asarray(report.info.pose[t], np.float64)
            truth = np.asarray(report.run.ground_truth, np.float64)[self.frame]
            d = np.hypot(*(pose[:, :2] - truth[:2]).T)
            self.nearest_m = float(d.min())
            turn = np.angle(np.exp(1j * (pose[int(np.argmin(d)), 2] - truth[2])))
            self.nearest_heading_deg = float(np.degrees(turn))
            self.within = {f"approach_within_{r}m": int(np.sum(d <= r))
                           for r in APPROACH_RADII}


def simulate_loop(file: Path, length_m: float, seed: int, config, course: str = "mars-yard-a",
                  max_frames: int | None = None, margin_per_m: float = 0.1, vo_noise=None):
    """(Run, config) of a loop driven by the trajectory ``file``: the config's map margin
    around the VO path raised to at least ``margin_per_m`` times the loop length, so that a
    path the filter corrects by the VO's drift stays on the map."""
    margin = max(config.map.margin, margin_per_m * length_m)
    config = apply_overrides(config, [f"map.margin={margin:g}"])
    run, _ = simulate_path(file, seed=seed, course=course, params=localmap_params(config),
                           max_frames=max_frames, vo_noise=vo_noise)
    return run, config


def planned(loop: Loop, particles: list[int], proposals: list[str], informed_max: float,
            informed_particles: list[int] | None = None) -> list[tuple[str, int]]:
    """The (proposal, J) runs of ``loop``: the informed proposal only up to ``informed_max``
    metres, at ``informed_particles`` where given."""
    return [(proposal, J) for proposal in proposals
            if proposal != "informed" or loop.length_m <= informed_max
            for J in ((informed_particles or particles) if proposal == "informed" else particles)]


def run_loop(loop: Loop, seed: int, config, particles: list[int], proposals: list[str],
             informed_max: float, informed_particles: list[int] | None = None,
             max_frames: int | None = None, course: str = "mars-yard-a",
             margin_per_m: float = 0.1, vo_noise=None, on_row=None,
             progress: bool = False, skip: Collection[tuple[str, int]] = ()) -> list[dict]:
    """Every (proposal, J) run of one loop at one seed (``planned``, less those in ``skip``),
    as result rows. The map's margin around the VO path is at least ``margin_per_m`` times
    the loop length, so that a path the filter corrects by the VO's drift stays on the map.
    vo_noise: that of ``course`` if None. progress: a line on stderr per chunk of frames
    filtered."""
    todo = [x for x in planned(loop, particles, proposals, informed_max, informed_particles)
            if x not in skip]
    if not todo:
        return []
    run, config = simulate_loop(loop.file, loop.length_m, seed, config, course, max_frames,
                                margin_per_m, vo_noise)
    revisit = loops.find_revisit(run.ground_truth, START_M, 0.5 * loop.length_m)
    rows = []
    for proposal, J in todo:
        cfg = apply_overrides(config, [f"filter.particles={J}", f"filter.proposal={proposal}",
                                       f"filter.seed={seed}"])
        row = {"loop": loop.name, "kind": loop.kind, "length_m": loop.length_m,
               "seed": seed, "proposal": proposal, "particles": J,
               "frames": run.num_frames, "local_maps": run.num_local_maps}
        if revisit is None:
            row.update(closed=None, note="no revisit within the radius in the driven run")
        else:
            t0 = time.perf_counter()
            cloud = ApproachCloud(approach_frame(run.ground_truth, revisit,
                                                 localmap_params(config).max_range))
            res = slam.run_slam(run, cfg, progress=_chunk_lines(
                f"{loop.name} seed {seed} {proposal} J={J}", t0) if progress else None,
                on_chunk=cloud)
            row.update(revisit=list(revisit), store=res.store, map_margin_m=config.map.margin,
                       extent_violations=res.extent_violations,
                       filter_seconds=res.seconds, wall_seconds=time.perf_counter() - t0,
                       peak_rss_mib=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                       approach_frame=cloud.frame, approach_nearest_m=cloud.nearest_m,
                       approach_nearest_heading_deg=cloud.nearest_heading_deg,
                       **cloud.within, **score(run, res, revisit))
        rows.append(row)
        if on_row:
            on_row(row)
    return rows


# The settings that decide what a run computes: a resumed file must have the same (a file
# written before a setting existed was made at its value in RUN_SETTING_BEFORE).
RUN_SETTINGS = ("config", "set", "store", "course", "overlap", "margin_per_m", "radius",
                "vo_scale", "vo_failures", "noise_scale")
RUN_SETTING_BEFORE = {"vo_scale": 1.0, "vo_failures": 1.0, "noise_scale": 1.0}


def resumed_rows(file: Path | None, settings: dict) -> list[dict]:
    """The rows of an earlier ``--json`` ``file`` to resume (none if it does not exist yet);
    an error naming the setting where its run settings differ from ``settings``."""
    if file is None:
        raise SystemExit("--resume needs --json FILE: the runs to keep are read from it")
    if not Path(file).exists():
        return []
    rows = read_rows([file])
    before = json.loads(Path(file).read_text()).get("settings", {})
    for name in RUN_SETTINGS:
        made = before.get(name, RUN_SETTING_BEFORE.get(name))
        if made != settings[name]:
            raise SystemExit(f"{file}: --resume with --{name.replace('_', '-')} "
                             f"{settings[name]!r}, but its runs were made with {made!r}")
    return rows


def _chunk_lines(label: str, t0: float):
    """A ``run_slam`` progress callback: one line on stderr per call (a chunk of frames)."""
    def report(done: int, total: int) -> None:
        print(f"  {label}: frame {done}/{total}, {time.perf_counter() - t0:.0f} s",
              file=sys.stderr, flush=True)
    return report


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--circles", type=float, nargs="*", default=[50, 100, 200, 400],
                    help="circle perimeters, m")
    ap.add_argument("--kitti", type=Path, nargs="*", default=[], help="KITTI pose files")
    ap.add_argument("--kitti-lengths", type=float, nargs="*", default=[300, 600],
                    help="loop lengths to cut from each KITTI file, m (the nearest found)")
    ap.add_argument("--particles", type=int, nargs="+", default=[20, 200])
    ap.add_argument("--proposals", nargs="+", default=["motion", "informed"])
    ap.add_argument("--informed-max-length", type=float, default=float("inf"),
                    help="run the informed proposal only on loops up to this length, m")
    ap.add_argument("--informed-particles", type=int, nargs="+",
                    help="J for the informed proposal (default: --particles)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--store", default="auto", choices=["dense", "shared", "window", "auto"])
    ap.add_argument("--course", default="mars-yard-a", help="world kind and VO noise")
    add_vo_arguments(ap)
    ap.add_argument("--overlap", type=float, default=20.0, help="metres driven past the loop")
    ap.add_argument("--margin-per-m", type=float, default=0.1,
                    help="map margin (m) per metre of loop, at least [map] margin")
    ap.add_argument("--radius", type=float, default=2.0, help="revisit radius of KITTI cuts, m")
    ap.add_argument("--config", type=Path, help="TOML config; a Table I config's tables for "
                    "--course apply (configs/table1.toml: that course's calibrated noise)")
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--json", type=Path, help="write settings and every run here")
    ap.add_argument("--plot", type=Path, help="write the closure plot here (PNG)")
    ap.add_argument("--progress", action="store_true",
                    help="a line on stderr per chunk of frames filtered")
    ap.add_argument("--resume", action="store_true",
                    help="keep the runs already in --json and run only the others (the "
                    "settings that decide a run must be the file's)")
    ap.add_argument("--verdict", choices=sorted(VERDICTS), default="best",
                    help="the path the summary and plot judge: the final best particle's (the "
                    "paper's), its densest particle's ([filter] estimate = \"mode\") or the "
                    "mean over that one's 1 m neighbourhood (\"mode_mean\"); each run's line "
                    "gives all three")
    ap.add_argument("--from-json", type=Path, nargs="+",
                    help="run nothing: summarise (and --plot) the rows of these --json files")
    args = ap.parse_args(argv)
    missing = [str(f) for f in args.kitti if not Path(f).is_file()]
    if missing:
        raise SystemExit(f"--kitti: no such pose file: {', '.join(missing)} (relative paths are "
                         f"from {Path.cwd()})")
    if args.from_json:
        rows = read_rows(args.from_json)
        try:
            print_summary(rows, args.verdict)
        except ValueError as err:
            raise SystemExit(f"--from-json: {err}") from None
        if args.plot:
            plot(rows, args.plot, args.verdict)
        return 0
    env = environment()
    config = scaled_alphas(layered_config(args.config, args.course,
                                          args.set + [f"map.store={args.store}"], courses=COURSES),
                           args.noise_scale)
    noise = vo_noise(args.course, args.vo_scale, args.vo_failures)
    print(f"# {env['date']} | {env['cpus']} cpus | jax {env['jax']}", flush=True)
    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
    settings["kitti"] = [str(p) for p in args.kitti]
    rows = resumed_rows(args.json, settings) if args.resume else []

    def write() -> None:
        if args.json:
            args.json.write_text(json.dumps({"settings": settings, "environment": env,
                                             "rows": rows}, indent=1, default=float))

    def on_row(r: dict) -> None:
        rows.append(r)
        if r["closed"] is None:
            print(f"{r['loop']:>16} seed {r['seed']}: {r['note']}", flush=True)
        else:
            print(f"{r['loop']:>16} seed {r['seed']} {r['proposal']:>8} J={r['particles']:<5} "
                  f"error {r['error_m']:6.2f} m offset {r['map_offset_m']:5.2f} m "
                  f"{'CLOSED' if r['closed'] else 'open  '} | mode {r['mode_error_m']:6.2f} m "
                  f"offset {r['mode_map_offset_m']:5.2f} m "
                  f"{'CLOSED' if r['mode_closed'] else 'open  '} | mode mean "
                  f"{r['mode_mean_error_m']:6.2f} m offset {r['mode_mean_map_offset_m']:5.2f} m "
                  f"{'CLOSED' if r['mode_mean_closed'] else 'open  '} | "
                  f"VO {r['vo_error_m']:6.2f} m "
                  f"{'closed' if r['vo_closed'] else 'open'} | nearest particle before the "
                  f"revisit {r['approach_nearest_m']:.2f} m ({r['approach_within_1m']} within "
                  f"1 m) | {r['wall_seconds']:.0f} s, peak RSS {r['peak_rss_mib']:.0f} MiB",
                  flush=True)
        write()

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        todo = [circle_loop(folder, x, args.overlap) for x in args.circles]
        for file in args.kitti:
            todo += kitti_loops(folder, file, args.kitti_lengths, args.radius, args.overlap)
        for loop in todo:
            for seed in args.seeds:
                done = {(r["proposal"], r["particles"]) for r in rows
                        if (r["loop"], r["seed"]) == (loop.name, seed)}
                run_loop(loop, seed, config, args.particles, args.proposals,
                         args.informed_max_length, args.informed_particles, course=args.course,
                         margin_per_m=args.margin_per_m, vo_noise=noise, on_row=on_row,
                         progress=args.progress, skip=done)
    summ = print_summary(rows, args.verdict)
    settings["summary"] = {k: {"rates": {str(x): v for x, v in s["rates"].items()},
                               "longest": s["longest"]} for k, s in summ.items()}
    write()
    if args.plot:
        plot(rows, args.plot, args.verdict)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
