"""Map reuse on the simulator: is run B, started in run A's finished map, at least as accurate
as A itself (and as B without the map)?

    python -m experiments.prior_map --out results/prior_map [--courses ...] [--seeds 0 1]
        [--max-frames N] [--sigma 0.5,0.5,0.1] [--config configs/table1.toml]
        [--set map.axes=start]

For each course and seed s:

* A: ``gslam run --course C --seed s`` (the simulator's course, world and noise of seed s);
* B: the same course and world (seed s) driven again with the VO and sensor noise of seed
  s + 100, written as a Run file (``gslam run --seed`` would change the course and the world
  too, so B is built here from the simulator's two halves, ``drive_course`` and ``sense_run``);
* B plain: ``gslam run B.npz``; B on A's map: ``gslam run B.npz --prior-map A --start X,Y,TH``
  with and without ``--start-sigma``.

B's start in A's frame: A's filter starts at A's true first pose (the simulator's Run gives it
as ``initial_pose``), so A's map frame is the simulator's world frame, exactly at the start;
B drives the same course, so its true start in that frame is B's ``initial_pose`` (read from
the Run file, printed in the commands). With ``--config`` every run (A, B's local maps and B's
runs) uses that config, a Table I config's ``[course.<name>.*]`` tables resolved per course and
written to OUT/<course>-<seed>/config.toml; ``--set`` settings apply to every run the same way
(``--b-set``: to B's runs only). Every command is run through ``gslam_jax.app.cli.main``
and written to OUT/commands.txt; the figures come from each run's summary.json (RMS after the
rigid fit, over every frame).
"""

from __future__ import annotations

import argparse
import math
import json
import time
from pathlib import Path

import numpy as np

from gslam_jax.app import cli


def make_b(course: str, seed: int, noise_seed: int, max_frames: int | None, path: Path,
           config: Path | None = None) -> None:
    """Run file of ``course`` with the course and world of ``seed`` and the VO and sensor noise
    of ``noise_seed``; its local maps made as ``config`` (a TOML file; None: the defaults)
    makes them."""
    from gslam_jax.config import layered_config
    from gslam_jax.datasets.sim import drive_course, sense_run
    from gslam_jax.run import save_run
    from gslam_jax.sim.courses import COURSES, make_course
    from gslam_jax.sim.environments import world_for_course
    from gslam_jax.sim.vonoise import VO_PROFILES
    from gslam_jax.vo.localmap import localmap_params

    odo = drive_course(make_course(course, seed), noise_seed, VO_PROFILES[course],
                       max_frames=max_frames)
    world = world_for_course(odo.course, seed)
    params = localmap_params(layered_config(config, course, courses=COURSES), "points")
    run, _ = sense_run(odo, world, noise_seed, params)
    save_run(path, run)


def gslam(args: list[str], log: Path) -> dict:
    """``gslam`` with ``args`` (recorded in ``log``); the summary.json of its --out."""
    with open(log, "a") as f:
        f.write("gslam " + " ".join(args) + "\n")
    code = cli.main(args)
    if code:
        raise SystemExit(f"gslam {' '.join(args)} exited with {code}")
    return json.loads((Path(args[args.index("--out") + 1]) / "summary.json").read_text())


def one(course: str, seed: int, out: Path, max_frames: int | None, sigma: str,
        b_set: tuple[str, ...] = (), located: bool = False,
        config: Path | None = None, overrides: tuple[str, ...] = ()) -> dict:
    """A, B plain, B on A's map (exact start, then spread by ``sigma``) for one course/seed;
    ``b_set``: ``--set KEY=VALUE`` settings of B's runs only. With
    ``located``, also B on A's map with no --start (the start located from B's first metres:
    ``relocalise``), and the located start's error against B's true start in A's frame.
    ``config``: a TOML config of every run, its course tables resolved for ``course`` (None:
    the defaults); ``overrides``: ``section.key=value`` settings of every run, over it."""
    from gslam_jax.config import config_to_toml, layered_config
    from gslam_jax.sim.courses import COURSES
    from gslam_jax.run import load_run

    d = out / f"{course}-{seed}"
    d.mkdir(parents=True, exist_ok=True)
    log = out / "commands.txt"
    frames = [] if max_frames is None else ["--max-frames", str(max_frames)]
    row: dict = {"course": course, "seed": seed, "b_noise_seed": seed + 100,
                 "b_set": list(b_set), "config": None if config is None else str(config),
                 "set": list(overrides)}
    resolved = None
    if config is not None or overrides:  # this course's config: every run reads one file
        resolved = d / "config.toml"
        resolved.write_text(config_to_toml(layered_config(config, course, list(overrides),
                                                          courses=COURSES)))
    common = [] if resolved is None else ["--config", str(resolved)]
    t0 = time.perf_counter()
    a = gslam(["run", "--course", course, "--seed", str(seed), *frames, *common,
               "--out", str(d / "A"), "--overwrite"], log)
    b_file = d / "B.npz"
    make_b(course, seed, seed + 100, max_frames, b_file, resolved)
    make_b_args = [json.dumps(course), seed, seed + 100, max_frames, json.dumps(str(b_file))]
    if resolved is not None:
        make_b_args.append(json.dumps(str(resolved)))
    with open(log, "a") as f:
        f.write("# B.npz: python -c 'from experiments.prior_map import make_b; make_b("
                + ", ".join(map(str, make_b_args)) + ")'\n")
    start = np.asarray(load_run(b_file).start_pose(), np.float64)
    start_text = ",".join(repr(float(v)) for v in start)
    settings = common + [arg for kv in b_set for arg in ("--set", kv)]
    plain = gslam(["run", str(b_file), *settings, "--out", str(d / "B-plain"), "--overwrite"],
                  log)
    prior = gslam(["run", str(b_file), *settings, "--prior-map", str(d / "A"), "--start",
                   start_text, "--out", str(d / "B-prior"), "--overwrite"], log)
    spread = gslam(["run", str(b_file), *settings, "--prior-map", str(d / "A"), "--start",
                    start_text, "--start-sigma", sigma, "--out", str(d / "B-prior-sigma"),
                    "--overwrite"], log)
    if located:  # a start the map cannot tell unambiguously is refused (exit code 2)
        try:
            found = gslam(["run", str(b_file), *settings, "--prior-map", str(d / "A"), "--out",
                           str(d / "B-located"), "--overwrite"], log)
        except SystemExit as refused:
            found = None
            row.update(b_located_refused=str(refused))
    if located and found is not None:
        got = np.asarray(found["prior_map"]["start"], np.float64)
        row.update(b_located_rms=found["slam_rms_m"],
                   located_start_error_m=float(np.hypot(*(got[:2] - start[:2]))),
                   located_start_error_deg=abs(math.degrees(math.remainder(
                       float(got[2] - start[2]), 2 * math.pi))),
                   located_sigma=found["prior_map"]["start_sigma"])
    for name in ("A", "B-plain", "B-prior", "B-located"):
        summary = d / name / "summary.json"
        if summary.is_file():  # the run's own map checked against itself (gslam run)
            check = json.loads(summary.read_text()).get("map_consistency")
            if check is not None:
                row[f"consistent_{name}"] = check["consistent"]
    row.update(frames=a["frames"], a_rms=a["slam_rms_m"], a_vo_rms=a["vo_rms_m"],
               b_vo_rms=plain["vo_rms_m"], b_plain_rms=plain["slam_rms_m"],
               b_prior_rms=prior["slam_rms_m"], b_prior_sigma_rms=spread["slam_rms_m"],
               cells_added=prior["prior_map"]["cells_added"],
               prior_known_cells=prior["prior_map"]["prior_known_cells"],
               seconds=time.perf_counter() - t0)
    print(json.dumps(row))
    return row


def _xy(folder: Path) -> np.ndarray:
    """Positions [T, 2] of a results folder's reported path (trajectory_tum.txt)."""
    return np.loadtxt(folder / "trajectory_tum.txt")[:, 1:3]


def agreement(out: Path, row: dict) -> dict:
    """How far B's paths lie from A's, frame by frame, in A's frame (no fit): B drives A's
    course on A's clock, so frame t is the same true pose in both runs, and plain B starts at
    the same true pose as A. A small distance with the prior: B is localised in A's map (and
    shares its errors)."""
    d = out / f"{row['course']}-{row['seed']}"
    a = _xy(d / "A")
    rms = {name: float(np.sqrt(np.mean(np.sum((_xy(d / name) - a) ** 2, axis=1))))
           for name in ("B-plain", "B-prior", "B-prior-sigma")}
    return {"b_plain_to_a_m": rms["B-plain"], "b_prior_to_a_m": rms["B-prior"],
            "b_prior_sigma_to_a_m": rms["B-prior-sigma"]}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--courses", nargs="+", default=["mars-yard-a", "arroyo-a", "maze"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--sigma", default="0.5,0.5,0.1", help="--start-sigma of the spread runs")
    ap.add_argument("--located", action="store_true",
                    help="also run B on A's map without --start (the start located)")
    ap.add_argument("--b-set", action="append", default=[], metavar="KEY=VALUE",
                    help="--set of B's runs (repeatable), e.g. filter.proposal=informed")
    ap.add_argument("--config", type=Path, default=None,
                    help="TOML config of every run (default: the defaults); a Table I config's "
                         "[course.<name>.*] tables apply per course")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="overrides",
                    help="--set of every run (repeatable, over --config), e.g. map.axes=start")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    table = args.out / "prior_map.json"
    if table.exists():
        rows = json.loads(table.read_text())
    done = {(r["course"], r["seed"]) for r in rows}
    for course in args.courses:
        for seed in args.seeds:
            if (course, seed) in done:
                continue
            rows.append(one(course, seed, args.out, args.max_frames, args.sigma,
                            tuple(args.b_set), args.located, args.config,
                            tuple(args.overrides)))
            table.write_text(json.dumps(rows, indent=1))
    rows = [{**r, **agreement(args.out, r)} for r in rows]
    table.write_text(json.dumps(rows, indent=1))
    print(f"{'course':12} {'seed':>4} {'A':>7} {'B VO':>7} {'B':>7} {'B+A':>7} {'B+A s':>7}"
          f" {'B-A':>7} {'B+A-A':>7} {'s-A':>7}")
    for r in rows:
        print(f"{r['course']:12} {r['seed']:>4} {r['a_rms']:7.3f} {r['b_vo_rms']:7.3f} "
              f"{r['b_plain_rms']:7.3f} {r['b_prior_rms']:7.3f} {r['b_prior_sigma_rms']:7.3f} "
              f"{r['b_plain_to_a_m']:7.3f} {r['b_prior_to_a_m']:7.3f} "
              f"{r['b_prior_sigma_to_a_m']:7.3f}")


if __name__ == "__main__":
    main()
