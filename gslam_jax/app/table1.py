"""Table I of the paper on the simulated courses: distance, VO-only RMS, Gamma-SLAM RMS.

``gslam table1`` and ``experiments/table1.py`` call ``main``. RMS is position error after the
least-squares 2-D rigid fit to ground truth (paper 7.1), over every frame.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from gslam_jax.app.outfile import check_output_file, write_text_atomic
from gslam_jax.config import (Config, ConfigError, apply_overrides, config_to_toml,
                              load_table_config)
from gslam_jax.driver import slam
from gslam_jax.evaluation import metrics
from gslam_jax.sim.courses import COURSES

__all__ = ["PAPER_TABLE1", "run_course", "main"]

# Paper Table I: distance (m), VO-only RMS (m), Gamma-SLAM RMS (m). The text of 7.2 repeats the
# Arroyo Seco rows (0.42 vs 0.34 m on course A, 1.22 vs 0.32 m on course B).
PAPER_TABLE1 = {
    "mars-yard-a": (164, 1.24, 0.29),
    "mars-yard-b": (204, 1.12, 0.21),
    "arroyo-a": (335, 0.42, 0.34),
    "arroyo-b": (406, 1.22, 0.32),
    "maze": (543, 1.98, 0.65),
}


def run_course(course: str, seed: int, config: Config, progress=None) -> dict:
    """Simulate one course and run Gamma-SLAM on it; returns the Table I row for this seed."""
    from gslam_jax.app.pipeline import Source, load_source  # the source step of ``gslam run``

    t0 = time.perf_counter()
    run = load_source(Source(course=course, seed=seed), config).run
    sim_s = time.perf_counter() - t0
    res = slam.run_slam(run, config, progress=progress)
    gt = run.ground_truth
    return {"course": course, "seed": seed, "distance_m": run.distance(),
            "vo_rms_m": metrics.rms_after_fit(res.vo_path, gt),
            "slam_rms_m": metrics.rms_after_fit(res.path, gt),
            "resampling_events": int(res.resampled.sum()),
            "extent_violations": res.extent_violations,
            "sim_seconds": sim_s, "filter_seconds": res.seconds + res.compile_seconds}


def main(courses: list[str], seeds: list[int], particles: int | None = None,
         config_path: Path | None = None, json_path: Path | None = None,
         quick: bool = False, overrides: list[str] | None = None,
         overwrite: bool = False) -> int:
    """Run and print Table I; ``particles`` None takes each course's filter.particles from the
    config (200 where it does not set it); ``quick``: Mars Yard A, one seed, J <= 100;
    ``overrides`` (``section.key=value``) apply to every course after its course tables.
    Every course's config gets the checks of ``gslam run`` and ``json_path`` is checked
    before any course runs; the JSON is written atomically."""
    from gslam_jax.app.pipeline import Source, check_inputs
    from gslam_jax.driver.machine import environment

    shared, per_course = load_table_config(config_path, COURSES)
    if quick:
        courses, seeds = ["mars-yard-a"], [0]

    def course_config(course: str) -> Config:
        c = apply_overrides(per_course.get(course, shared), overrides or [])
        j = c.filter.particles if particles is None else particles
        j = min(j, 100) if quick else j
        return dataclasses.replace(c, filter=dataclasses.replace(c.filter, particles=j))

    if json_path:
        check_output_file(json_path, "--json", overwrite)
    for course in courses:
        try:
            check_inputs(Source(course=course, seed=seeds[0]), course_config(course))
        except ConfigError as err:
            where = f"{config_path}: " if config_path else ""
            raise ConfigError(f"{where}course {course}: {err}") from err
    used = sorted({course_config(c).filter.particles for c in courses})
    particles_text = ", ".join(map(str, used))
    env = environment()
    print(f"Table I on simulated courses, J = {particles_text}, seeds {seeds}")
    print("  " + ", ".join(f"{k}: {env[k]}" for k in ("date", "processor", "cpus", "jax", "numpy")))
    rows = []
    for course in courses:
        for seed in seeds:
            config = course_config(course)
            r = run_course(course, seed, config)
            r["particles"] = config.filter.particles
            r["config"] = config_to_toml(config)
            rows.append(r)
            print(f"  {course:<12} seed {seed}: {r['distance_m']:6.1f} m  VO {r['vo_rms_m']:.3f} m  "
                  f"Gamma-SLAM {r['slam_rms_m']:.3f} m  ({r['filter_seconds']:.0f} s)", flush=True)
    print(f"\n{'course':<12} {'dist':>6} {'VO mean':>8} {'VO worst':>9} {'SLAM mean':>10} "
          f"{'SLAM worst':>11} {'ratio':>6} | paper: {'dist':>5} {'VO':>5} {'SLAM':>5}")
    for course in courses:
        rs = [r for r in rows if r["course"] == course]
        vo = np.array([r["vo_rms_m"] for r in rs])
        sl = np.array([r["slam_rms_m"] for r in rs])
        paper = PAPER_TABLE1.get(course, (np.nan,) * 3)
        print(f"{course:<12} {rs[0]['distance_m']:6.1f} {vo.mean():8.3f} {vo.max():9.3f} "
              f"{sl.mean():10.3f} {sl.max():11.3f} {np.max(sl / vo):6.2f} | "
              f"{paper[0]:>12} {paper[1]:5.2f} {paper[2]:5.2f}")
    if json_path:
        write_text_atomic(json_path, json.dumps({"environment": env,
                                                 "particles": used[0] if len(used) == 1
                                                 else used, "rows": rows}, indent=2), "--json")
    return 0
