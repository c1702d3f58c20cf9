"""Regenerate every figure of the headline results page (docs/results.md).

    python -m experiments.headline                       # every section, printed
    python -m experiments.headline --out docs/figures    # ... and headline.json, headline.md
                                                         #     and the page's images written there
    python -m experiments.headline --sections default kitti
    python -m experiments.headline --out docs/figures --page docs/results.md   # ... and the page

Sections, each the command a user would run and the figures the page quotes from it:

* ``default``: ``gslam run``, the built-in simulated course (Mars Yard A, J = 200): VO-only and
  Gamma-SLAM RMS, resampling events, the filter's time and real-time factor, the whole command's
  wall time.
* ``kitti``: the 51-frame KITTI clip through the front-end (``gslam run --source kitti
  --save-run``), then the filter on its Run file over filter seeds (``experiments.proposal_compare
  --proposals motion``): Gamma-SLAM's RMS over VO-only's, mean and worst, and on how many seeds
  the RMS and the final drift are under VO's.
* ``euroc``: the 20 static EuRoC frames: how far VO and Gamma-SLAM say the camera moved.
* ``table1``: the paper's Table I on the five simulated courses (``gslam table1 --config
  configs/table1.toml``) at ``--table1-particles`` over ``--table1-seeds``.
* ``loops``: the particles a loop needs (``experiments.loop_bound``): the chance that one of J
  particles is within 1 m of the truth when a loop of each length closes.

The output starts with the machine, the versions and the git commit; the page names the commit
its figures were generated at. ``--out DIR`` writes ``headline.json`` (every figure, the
environment and the commit), ``headline.md`` (the page's tables) and the images the page
shows; ``--page FILE`` writes each section's commands and table into FILE between its markers
``<!-- headline:NAME -->`` and ``<!-- /headline:NAME -->`` (and the commit and machine between
``<!-- headline:generated -->`` markers), leaving the prose around them as it is. The
real-data sections skip, saying so, where ``--data`` lacks their clip.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SECTIONS = ("default", "kitti", "euroc", "table1", "loops")
KITTI_CLIP, KITTI_SEQUENCE = "kitti-stereo-51", "seq1"
EUROC_CLIP = "euroc-v1_01-static-20"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("--sections", nargs="+", choices=SECTIONS, default=list(SECTIONS),
                    help="which sections to run (default: all)")
    ap.add_argument("--out", type=Path, help="write headline.json, headline.md and the "
                    "page's images into this folder (created; files in it replaced)")
    ap.add_argument("--page", type=Path, help="write the figures into this page between its "
                    "<!-- headline:NAME --> markers (docs/results.md)")
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data",
                    help="the folder holding the KITTI and EuRoC clips (default ../shared/data)")
    ap.add_argument("--kitti-seeds", type=int, default=16,
                    help="filter seeds 0..N-1 on the KITTI clip (default 16)")
    ap.add_argument("--table1-seeds", type=int, nargs="+", default=[0, 1, 2],
                    help="simulation seeds of Table I (default 0 1 2)")
    ap.add_argument("--table1-particles", type=int, default=200,
                    help="J of Table I (default 200)")
    ap.add_argument("--loop-draws", type=int, default=5000,
                    help="motion-model paths per seed of the loop bound (default 5000)")
    ap.add_argument("--max-frames", type=int,
                    help="cut the default run to its first N frames (a quick check, not the page)")
    ap.add_argument("--particles", type=int,
                    help="J of the default run (a quick check, not the page; default the "
                    "config's 200)")
    return ap.parse_args(argv)


def git_commit(root: Path = ROOT) -> str:
    """The checkout's commit, with ``+dirty`` where tracked files differ from it; "unknown"
    outside a git checkout."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True,
                              text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=root, capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+dirty" if dirty.strip() else "")


def gslam(args: list[str]) -> tuple[dict, list[str], float]:
    """``gslam ARGS`` in this process: the results folder's summary.json, the command's last
    printed lines (its own summary) and its wall time. Raises when it fails."""
    from gslam_jax.app.cli import main

    printed = io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(printed):
        code = main(args)
    wall = time.perf_counter() - t0
    lines = [ln for ln in printed.getvalue().replace("\r", "\n").splitlines() if ln.strip()]
    if code != 0:
        raise RuntimeError(f"gslam {' '.join(args)} exited {code}:\n" + "\n".join(lines[-20:]))
    out = Path(args[args.index("--out") + 1])
    return json.loads((out / "summary.json").read_text()), lines, wall


def _cli_summary(lines: list[str]) -> list[str]:
    """The lines ``gslam run`` prints after the filter (from "distance:" on)."""
    start = next((i for i, ln in enumerate(lines) if ln.startswith("distance:")), len(lines))
    return lines[start:]


def section_default(args: argparse.Namespace, work: Path) -> dict:
    """``gslam run``: the built-in default."""
    command = ["run", "--out", str(work / "default")]
    shown = "gslam run"
    if args.max_frames:
        command += ["--max-frames", str(args.max_frames)]
        shown += f" --max-frames {args.max_frames}"
    if args.particles:
        command += ["--set", f"filter.particles={args.particles}"]
        shown += f" --set filter.particles={args.particles}"
    s, lines, wall = gslam(command)
    figures = {k: s.get(k) for k in ("source", "frames", "distance_m", "particles", "vo_rms_m",
                                     "slam_rms_m", "vo_drift_pct", "slam_drift_pct",
                                     "resampling_events", "filter_seconds", "compile_seconds",
                                     "log_seconds", "realtime_factor")}
    figures["wall_seconds"] = wall
    figures["ratio"] = s["slam_rms_m"] / s["vo_rms_m"]
    figures["map_consistency"] = _consistency_note(s.get("map_consistency"))
    table = [("distance", f"{s['distance_m']:.0f} m, {s['frames']} frames, J = {s['particles']}"),
             ("VO-only RMS", f"{s['vo_rms_m']:.3f} m"),
             ("Gamma-SLAM RMS", f"{s['slam_rms_m']:.3f} m ({figures['ratio']:.2f}x VO-only's)"),
             ("final drift", _drift(s)),
             ("resampling events", str(s["resampling_events"])),
             ("filter time", _filter_time(s)),
             ("whole command", f"{wall:.0f} s wall (simulation, compilation, filter, map check, "
                               "figures)"),
             ("map check", figures["map_consistency"])]
    return {"title": "The default run", "commands": [shown], "figures": figures,
            "table": table, "printed": _cli_summary(lines),
            "images": {"default_maps.png": work / "default" / "maps_vo_vs_slam.png"}}


def _drift(s: dict) -> str:
    """The final drift of both paths, or the summary's note on why there is none."""
    if s.get("slam_drift_pct") is None:
        return s.get("drift_note", "none (no ground truth)")
    return f"VO-only {s['vo_drift_pct']:.2f} %, Gamma-SLAM {s['slam_drift_pct']:.2f} %"


def _filter_time(s: dict) -> str:
    """The filter's time as ``gslam run`` reports it: compilation and the frames after it."""
    after = s["filter_seconds"]
    text = f"{s['compile_seconds']:.1f} s first chunk with compilation"
    if after > 0.01:
        text += f", {after:.1f} s the rest"
    return text + f"; {s['log_seconds']:.0f} s of log, real-time factor {s['realtime_factor']:.2f}"


def _consistency_note(c: dict | None) -> str:
    """``summary.json``'s ``map_consistency`` in a line."""
    if not c:
        return "not run"
    verdict = "consistent" if c.get("consistent") else "terrain mapped twice"
    return (f"{verdict}: {c.get('revisits_checked', 0)} revisited stretches checked, "
            f"{len(c.get('doubled', []))} placed elsewhere")


def section_kitti(args: argparse.Namespace, work: Path) -> dict:
    """The KITTI clip: one run as a user runs it, then the filter over ``--kitti-seeds`` seeds
    on its Run file."""
    from experiments.proposal_compare import case_row
    from gslam_jax import load_run
    from gslam_jax.config import layered_config

    clip = args.data / KITTI_CLIP
    if not clip.is_dir():
        return _skipped("The KITTI clip against VO-only", clip)
    run_file = work / "k51.npz"
    s, lines, wall = gslam(["run", "--source", "kitti", "--path", str(clip), "--sequence",
                            KITTI_SEQUENCE, "--save-run", str(run_file), "--out",
                            str(work / "kitti")])
    run, config = load_run(run_file), layered_config(None, None, [])
    seeds = list(range(args.kitti_seeds))
    rows = [case_row("k51", run, config, 1.0, "motion", seed) for seed in seeds]
    ratio = np.array([r["ratio"] for r in rows])
    rms_under = sum(r["slam_rms_m"] < r["vo_rms_m"] for r in rows)
    drift_under = sum(r["slam_drift_pct"] < r["vo_drift_pct"] for r in rows)
    both = sum(r["slam_rms_m"] < r["vo_rms_m"] and r["slam_drift_pct"] < r["vo_drift_pct"]
               for r in rows)
    seed_text = f"0-{seeds[-1]}" if len(seeds) > 1 else "0"
    figures = {"distance_m": s["distance_m"], "frames": s["frames"], "particles": s["particles"],
               "vo_rms_m": s["vo_rms_m"], "slam_rms_m": s["slam_rms_m"],
               "vo_drift_pct": s.get("vo_drift_pct"), "slam_drift_pct": s.get("slam_drift_pct"),
               "resampling_events": s["resampling_events"], "wall_seconds": wall,
               "seeds": seeds, "ratio_mean": float(ratio.mean()),
               "ratio_worst": float(ratio.max()), "ratio_best": float(ratio.min()),
               "rms_under_vo": int(rms_under), "drift_under_vo": int(drift_under),
               "both_under_vo": int(both), "rows": rows}
    n = len(rows)
    table = [("the run (filter seed 0)",
              f"VO-only {s['vo_rms_m']:.3f} m, Gamma-SLAM {s['slam_rms_m']:.3f} m RMS; "
              f"final drift {_drift(s)}; "
              f"{s['resampling_events']} resampling events; {wall:.0f} s wall"),
             (f"filter seeds {seed_text}",
              f"Gamma-SLAM RMS / VO-only's: mean {ratio.mean():.2f}x, worst {ratio.max():.2f}x, "
              f"best {ratio.min():.2f}x"),
             ("under VO-only's", f"RMS on {rms_under} of {n}, final drift on {drift_under} of "
                                 f"{n}, both on {both} of {n}")]
    seeds_arg = " ".join(map(str, seeds)) if n <= 4 else f"$(seq 0 {seeds[-1]})"
    commands = [f"gslam run --source kitti --path ../shared/data/{KITTI_CLIP} --sequence "
                f"{KITTI_SEQUENCE} --save-run k51.npz --out results/kitti",
                f"python -m experiments.proposal_compare --runs k51.npz --proposals motion "
                f"--seeds {seeds_arg}"]
    return {"title": "The KITTI clip against VO-only", "commands": commands,
            "figures": figures, "table": table, "printed": _cli_summary(lines),
            "images": {"kitti_errors.png": work / "kitti" / "errors.png"}}


def section_euroc(args: argparse.Namespace, work: Path) -> dict:
    """The static EuRoC clip: the camera does not move; how far VO and Gamma-SLAM say it did."""
    clip = args.data / EUROC_CLIP
    if not clip.is_dir():
        return _skipped("The static EuRoC clip", clip)
    out = work / "euroc"
    s, lines, wall = gslam(["run", "--source", "euroc", "--path", str(clip), "--out", str(out)])
    moved = {}
    for name, file in (("vo", "vo_tum.txt"), ("slam", "trajectory_tum.txt")):
        xyz = np.loadtxt(out / file)[:, 1:4]
        moved[name] = float(np.linalg.norm(xyz[-1] - xyz[0]))
    figures = {"frames": s["frames"], "distance_m": s["distance_m"], "vo_end_m": moved["vo"],
               "slam_end_m": moved["slam"], "resampling_events": s["resampling_events"],
               "wall_seconds": wall}
    table = [("frames", f"{s['frames']} of a MAV standing still"),
             ("distance by VO", f"{100 * s['distance_m']:.2f} cm"),
             ("last pose from the first", f"VO-only {100 * moved['vo']:.2f} cm, Gamma-SLAM "
                                          f"{100 * moved['slam']:.2f} cm"),
             ("resampling events", str(s["resampling_events"]))]
    return {"title": "The static EuRoC clip", "figures": figures, "table": table,
            "commands": [f"gslam run --source euroc --path ../shared/data/{EUROC_CLIP} "
                         "--out results/euroc"],
            "printed": _cli_summary(lines), "images": {}}


def section_table1(args: argparse.Namespace, work: Path) -> dict:
    """Table I of the paper at ``--table1-particles`` over ``--table1-seeds``."""
    from gslam_jax.app.table1 import PAPER_TABLE1, main

    config = ROOT / "configs" / "table1.toml"
    path = work / "table1.json"
    printed = io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(printed):
        code = main(list(PAPER_TABLE1), args.table1_seeds, args.table1_particles, config, path)
    wall = time.perf_counter() - t0
    if code != 0:
        raise RuntimeError("gslam table1 failed:\n" + printed.getvalue()[-2000:])
    rows = json.loads(path.read_text())["rows"]
    for r in rows:
        r.pop("config", None)
    table, per_course = [], {}
    for course, (dist, vo_paper, slam_paper) in PAPER_TABLE1.items():
        rs = [r for r in rows if r["course"] == course]
        vo = np.array([r["vo_rms_m"] for r in rs])
        sl = np.array([r["slam_rms_m"] for r in rs])
        per_course[course] = {"distance_m": rs[0]["distance_m"], "vo_mean_m": float(vo.mean()),
                              "slam_mean_m": float(sl.mean()), "slam_worst_m": float(sl.max())}
        table.append((course, f"{rs[0]['distance_m']:.0f} m", f"{slam_paper:.2f} ({vo_paper:.2f})",
                      f"{sl.mean():.3f} / {sl.max():.3f}", f"{vo.mean():.2f}"))
    seeds = " ".join(map(str, args.table1_seeds))
    return {"title": "Table I on the simulated courses",
            "commands": [f"gslam table1 --config configs/table1.toml --particles "
                         f"{args.table1_particles} --seeds {seeds}"],
            "figures": {"particles": args.table1_particles, "seeds": args.table1_seeds,
                        "courses": per_course, "rows": rows, "wall_seconds": wall},
            "header": ("course", "length", "paper: Gamma-SLAM (VO-only) RMS, m",
                       "Gamma-SLAM RMS mean / worst, m", "VO-only RMS mean, m"),
            "table": table, "printed": [], "images": {}}


def section_loops(args: argparse.Namespace, work: Path) -> dict:
    """The flat-weight bound: the chance that one of J particles is within 1 m of the truth
    when a loop closes, on circles of the Arroyo course's VO and calibrated noise."""
    from experiments.loop_bound import main

    path = work / "loops.json"
    argv = ["--course", "arroyo-a", "--config", str(ROOT / "configs" / "table1.toml"),
            "--circles", "200", "400", "800", "1000", "--seeds", "0", "1", "2", "3", "4",
            "--draws", str(args.loop_draws), "--particles", "200", "2000", "--json", str(path)]
    printed = io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(printed):
        main(argv)
    wall = time.perf_counter() - t0
    summary = json.loads(path.read_text())["summary"]
    table = [(name, f"{s['spread_m']:.1f} m", f"{s['vo_miss_median_m']:.1f} m",
              f"{100 * s['chance_gauss']['200']:.0f} %", f"{100 * s['chance_gauss']['2000']:.0f} %",
              _particles(s["particles_for_share_gauss"]))
             for name, s in summary.items()]
    shown = " ".join(a if not a.startswith(str(ROOT)) else str(Path(a).relative_to(ROOT))
                     for a in argv[:-2])
    return {"title": "How many particles a loop needs",
            "commands": [f"python -m experiments.loop_bound {shown}"],
            "figures": {"summary": summary, "wall_seconds": wall},
            "header": ("loop", "the cloud's spread (median)", "VO's miss (median)",
                       "J = 200: chance of a particle within 1 m",
                       "J = 2000", "J for 80 %"),
            "table": table, "printed": [], "images": {}}


def _particles(j: float) -> str:
    return "over 10^6" if not math.isfinite(j) or j > 1e6 else f"{j:.0f}"


def _skipped(title: str, clip: Path) -> dict:
    return {"title": title, "skipped": f"{clip} not found (see shared/data/README.md)",
            "commands": [], "figures": {}, "table": [], "printed": [], "images": {}}


RUNNERS: dict[str, Callable[[argparse.Namespace, Path], dict]] = {
    "default": section_default, "kitti": section_kitti, "euroc": section_euroc,
    "table1": section_table1, "loops": section_loops}


def markdown(section: dict) -> str:
    """A section as the page shows it: its commands, then its figures as a table."""
    if section.get("skipped"):
        return f"Skipped: {section['skipped']}.\n"
    lines = ["```bash", *section["commands"], "```", ""]
    header = section.get("header", ("figure", "value"))
    lines += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(map(str, row)) + " |" for row in section["table"]]
    return "\n".join(lines) + "\n"


def between_markers(page: str, name: str, text: str) -> str:
    """``page`` with what lies between ``<!-- headline:NAME -->`` and ``<!-- /headline:NAME -->``
    replaced by ``text``; a page without that pair of markers is an error naming them."""
    start, end = f"<!-- headline:{name} -->", f"<!-- /headline:{name} -->"
    i, j = page.find(start), page.find(end)
    if i < 0 or j < i:
        raise ValueError(f"the page has no {start} ... {end} pair")
    return page[:i + len(start)] + "\n" + text.rstrip("\n") + "\n" + page[j:]


def generated_line(env: dict, commit: str) -> str:
    return f"Generated at commit `{commit}` on {environment_line(env, commit)}."


def environment_line(env: dict, commit: str) -> str:
    return (f"{env['date']} | {env['processor']} | {env['cpus']} cpus ({env['usable_cpus']} "
            f"usable) | python {env['python']} | jax {env['jax']} | numpy {env['numpy']} | "
            f"opencv {env['opencv']} | gslam-jax {env['gslam_jax']} | commit {commit}")


def write_outputs(args: argparse.Namespace, env: dict, commit: str, sections: dict) -> None:
    """``--out``'s headline.json and headline.md, and ``--page``'s figures, for the sections
    run so far."""
    if args.out:
        report = {"environment": env, "commit": commit, "sections": sections}
        (args.out / "headline.json").write_text(json.dumps(report, indent=1, default=float))
        text = [generated_line(env, commit), ""]
        text += [f"<!-- headline:{name} -->\n{markdown(s)}<!-- /headline:{name} -->\n"
                 for name, s in sections.items()]
        (args.out / "headline.md").write_text("\n".join(text))
    if args.page:
        page = between_markers(args.page.read_text(), "generated", generated_line(env, commit))
        for name, section in sections.items():
            page = between_markers(page, name, markdown(section))
        args.page.write_text(page)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    from gslam_jax import __version__
    from gslam_jax.driver.machine import environment

    if args.page:  # every marker checked before the sections run
        for name in ("generated", *args.sections):
            between_markers(args.page.read_text(), name, "")
    env = {**environment(), "gslam_jax": __version__}
    commit = git_commit()
    print(f"# {environment_line(env, commit)}", flush=True)
    sections = {}
    with tempfile.TemporaryDirectory(prefix="gslam-headline-") as tmp:
        for name in args.sections:
            work = Path(tmp) / name
            work.mkdir()
            t0 = time.perf_counter()
            section = RUNNERS[name](args, work)
            section["seconds"] = time.perf_counter() - t0
            print(f"\n## {section['title']} ({section['seconds']:.0f} s)", flush=True)
            print(markdown(section), flush=True)
            for line in section["printed"]:
                print(f"    {line}")
            if args.out:
                args.out.mkdir(parents=True, exist_ok=True)
                for image, source in section["images"].items():
                    if Path(source).is_file():
                        shutil.copyfile(source, args.out / image)
            section["images"] = sorted(section["images"])
            sections[name] = section
            write_outputs(args, env, commit, sections)  # after each: a later failure keeps these
    if args.out:
        print(f"\nwritten: {args.out}/headline.json, headline.md and the images", flush=True)
    if args.page:
        print(f"written: {args.page}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
