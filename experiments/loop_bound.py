"""How many particles a loop needs when the weights are flat round it: the sample-size bound
on ``experiments.loop_closure``'s closures.

Until the sensor first meets the map made at the loop's start, the particles have met only
their own maps, and on these loops their weights stay nearly flat (docs/notebook/results.md, "A
kilometre"): the cloud at the approach is then J draws of the motion model (eqs. 1-3) along
the VO. A loop closes only where one of them is within the closure's 1 m of the truth there
(``loop_closure``'s summary splits its closures by that). This experiment draws N such paths
without maps, on the truth and VO a ``loop_closure`` run of the same loop, seed and course
sees (``datasets.sim_path.drive_path``), with the config's motion noise (the fallback frames'
scaled as the filter scales them), and reports per seed the share p of draws within 1 m of
the truth at the approach frame (``loop_closure.approach_frame``), the expected number there
among J particles (J p) and the chance that at least one is (1 - (1 - p)^J): the closure rate
J particles can reach with flat weights. Per loop it gives the mean of that chance over the
seeds at each J, and the J at which it reaches 80 %. p is given twice: counted among the draws
(``p_within``: 0 where it is under 1 / N) and as the mass within 1 m of a Gaussian fitted to
them (``p_gauss``, ``gaussian_within``), with the cloud's spread (``spread_m``: the geometric
mean of its two standard deviations). Heading noise makes that spread grow as L^(3/2) round a
loop of length L, so where the truth lies inside the cloud p falls as L^-3 and the J a loop
needs grows as L^3 (docs/notebook/results.md, "How far the cloud reaches"). The filter's clouds at
J = 200 match the bound; at J = 2000 they left it both ways, the resampling keeping hypotheses
that flat draws do not (docs/notebook/results.md, "Which loops J particles can close").

What no tuning of the noise's level can buy: ``p_best_scale`` is the fit's mass within 1 m
with its width scaled by the factor that suits that seed's truth best (``best_scaled_within``),
an upper bound for any one factor on the alphas. For a round cloud centred r metres from the
truth it is about 1 / (e r^2): J = 200 particles have an 80 % chance of one within 1 m only
where the VO misses the approach by under about 6.8 m, whatever the noise.

    python -m experiments.loop_bound --course arroyo-a --config configs/table1.toml \\
        --circles 400 800 1000 --kitti ../shared/data/kitti-poses/00.txt \\
        --kitti-lengths 1000 --seeds 0 1 2 3 4 --particles 200 2000 --from-json runs.json

--from-json: ``loop_closure`` --json files whose runs (same loop and seed) are printed beside
the prediction: the particles the filter had within 1 m at the approach, and whether it
closed. --vo-scale F draws the VO with the course's noise times F (a better or worse VO),
--vo-failures F its failures' rate times F (0: none), and --noise-scale F multiplies the motion
model's alphas. With ``--set motion.noise_spread=S`` each draw takes its own factor on them, as
the filter's particles do (``rbpf.motion.particle_scales``); the cloud is then a mixture, and
``p_gauss`` (a single Gaussian's fit) does not describe it: read ``p_within``.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array, lax

from experiments.loop_closure import approach_frame
from experiments.loop_paths import START_M, add_vo_arguments, circle_loop, kitti_loops, vo_noise
from experiments.loop_summary import read_rows
from gslam_jax.config import layered_config
from gslam_jax.sim.courses import COURSES
from gslam_jax.datasets.sim_path import drive_path
from gslam_jax.driver.machine import environment
from gslam_jax.driver.sizing import motion_params
from gslam_jax.evaluation import loops
from gslam_jax.rbpf.motion import MotionParams, apply_motion, particle_scales, scaled
from gslam_jax.vo.localmap import localmap_params

SHARE = 0.8  # the closure rate the J of the summary reaches


@partial(jax.jit, static_argnames="draws")
def motion_draws(key: Array, start: Array, controls: Array, fallback: Array,
                 params: MotionParams, draws: int) -> Array:
    """[draws, 3] poses after every control of ``controls`` [T, 3] from ``start`` [3], each
    draw its own path of the motion model (eq. 1 with eqs. 2-3's noise, the filter's
    ``apply_motion``); a frame with ``fallback`` [T] set has its stds times
    ``params.fallback_scale``, as ``rbpf.step`` scales them. Frame t's normals come from
    ``fold_in(key, t)``."""

    def frame(pose: Array, xs: tuple[Array, Array, Array]) -> tuple[Array, None]:
        t, u, failed = xs
        p = scaled(params, jnp.where(failed, params.fallback_scale, 1.0))
        eps = jax.random.normal(jax.random.fold_in(key, t), pose.shape, pose.dtype)
        return apply_motion(pose, u, eps, p), None

    pose = jnp.broadcast_to(jnp.asarray(start, jnp.float32), (draws, 3))
    T = controls.shape[0]
    pose, _ = lax.scan(frame, pose, (jnp.arange(T), jnp.asarray(controls, jnp.float32),
                                     jnp.asarray(fallback, bool)))
    return pose


def chance_of_one(p: np.ndarray | float, J: float) -> np.ndarray:
    """1 - (1 - p)^J: the chance that at least one of J independent particles, each within
    the tolerance with probability p, is within it."""
    return -np.expm1(J * np.log1p(-np.minimum(p, 1.0 - 1e-16)))


def particles_for(p: np.ndarray, share: float = SHARE) -> float:
    """The J (real, >= 1) at which the mean over seeds of ``chance_of_one(p, J)`` reaches
    ``share``; inf where no finite J does (at least 1 - share of the seeds with p = 0)."""
    p = np.asarray(p, np.float64)
    if np.mean(p > 0) <= share:
        return float("inf")
    lo, hi = 0.0, 1.0
    while np.mean(chance_of_one(p, hi)) < share:
        lo, hi = hi, hi * 2.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if np.mean(chance_of_one(p, mid)) < share else (lo, mid)
    return max(hi, 1.0)


def gaussian_within(mean: np.ndarray, cov: np.ndarray, target: np.ndarray, radius: float,
                    rings: int = 24, angles: int = 48) -> float:
    """The mass within ``radius`` of ``target`` [2] of the Gaussian N(``mean``, ``cov``) (2-D),
    by the midpoint rule on a polar grid over the disc.

    ``loop_bound`` fits it to the draws (their mean and covariance): where few of N draws fall
    within the radius (a long loop: p below 1 / N), the count says only "under 1 / N", and the
    fit resolves it from the spread of all N draws, on the assumption that the cloud is
    Gaussian (a sum of many small steps' noise)."""
    inv, det = np.linalg.inv(cov), np.linalg.det(cov)
    r = (np.arange(rings) + 0.5) * (radius / rings)
    a = (np.arange(angles) + 0.5) * (2.0 * np.pi / angles)
    pts = np.asarray(target, np.float64)[:2] + np.stack(
        [r[:, None] * np.cos(a), r[:, None] * np.sin(a)], -1) - mean
    pdf = np.exp(-0.5 * np.einsum("...i,ij,...j->...", pts, inv, pts)) / (2 * np.pi * np.sqrt(det))
    return float(np.sum(pdf * r[:, None]) * (radius / rings) * (2.0 * np.pi / angles))


def best_scaled_within(mean: np.ndarray, cov: np.ndarray, target: np.ndarray, radius: float,
                       scales: np.ndarray = np.geomspace(1e-2, 1e2, 121)) -> tuple[float, float]:
    """The largest mass within ``radius`` of ``target`` that the Gaussian N(``mean``, k^2
    ``cov``) puts there over the factors k in ``scales``, and the k that does (the grid's
    best, refined by golden-section search between its neighbours).

    This is the cloud's shape with every noise std times one factor, chosen for each seed
    knowing where the truth lies: no single factor on the alphas gives that seed more (to the
    fit's accuracy). For an isotropic cloud and a truth r >> radius from its centre the best
    width is r / sqrt(2) and the mass radius^2 / (e r^2), so J particles reach a truth r away
    with chance at most 1 - (1 - radius^2 / (e r^2))^J. A truth within ``radius`` of the mean
    gives 1 (k -> 0)."""
    if np.hypot(*(np.asarray(target, np.float64)[:2] - mean)) < radius:
        return 1.0, 0.0

    def mass(log_k: float) -> float:
        return gaussian_within(mean, np.exp(2.0 * log_k) * cov, target, radius)

    logs = np.log(np.asarray(scales, np.float64))
    got = np.array([mass(x) for x in logs])
    i = int(np.argmax(got))
    lo, hi = logs[max(i - 1, 0)], logs[min(i + 1, logs.size - 1)]
    g = (np.sqrt(5.0) - 1.0) / 2.0
    best, best_log = got[i], logs[i]
    for _ in range(40):
        a, b = hi - g * (hi - lo), lo + g * (hi - lo)
        fa, fb = mass(a), mass(b)
        lo, hi = (lo, b) if fa >= fb else (a, hi)
        for x, f in ((a, fa), (b, fb)):
            if f > best:
                best, best_log = f, x
    return min(float(best), 1.0), float(np.exp(best_log))


def largest_miss(particles: float, share: float = SHARE, radius: float = loops.TOLERANCE
                 ) -> float:
    """The largest distance r between the truth and a round cloud's centre at which J =
    ``particles`` draws have chance ``share`` of one within ``radius``, with the cloud's width
    the best for that r (``best_scaled_within``): beyond it no noise level gives a seed that
    chance. About radius / sqrt(e p) for p = 1 - (1 - share)^(1 / J) (6.8 m at J = 200)."""
    def chance(r: float) -> float:
        p, _ = best_scaled_within(np.zeros(2), np.eye(2), np.array([r, 0.0]), radius)
        return float(chance_of_one(p, particles))

    lo, hi = radius, 2.0 * radius
    while chance(hi) >= share:
        lo, hi = hi, 2.0 * hi
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if chance(mid) >= share else (lo, mid)
    return lo


def against_runs(bounds: list[dict], runs: list[dict]) -> dict:
    """Per "proposal J=..", over the ``loop_closure`` runs of a (loop, seed) that ``bounds``
    has: the runs, the mean predicted chance of a particle within 1 m at the approach and the
    share of runs that had one, the mean predicted count there (J p) and the runs' mean."""
    p = {(b["loop"], b["seed"]): b["p_within"] for b in bounds if "p_within" in b}
    got = {}
    for r in runs:
        if (r["loop"], r["seed"]) in p and r.get("closed") is not None \
                and "approach_within_1m" in r:
            pr, J = p[(r["loop"], r["seed"])], r["particles"]
            got.setdefault(f"{r['proposal']} J={J}", []).append(
                (chance_of_one(pr, J), r["approach_within_1m"] > 0, J * pr,
                 r["approach_within_1m"]))
    return {name: dict(zip(("chance", "had_one", "expected", "count"),
                           np.mean(np.asarray(v, np.float64), axis=0).tolist()), runs=len(v))
            for name, v in sorted(got.items())}


def loop_bound(file: Path, length_m: float, seed: int, config, course: str, draws: int,
               vo_scale: float = 1.0, noise_scale: float = 1.0, vo_failures: float = 1.0
               ) -> dict:
    """One loop at one seed: the approach frame, the share of ``draws`` motion-model paths
    within ``loops.TOLERANCE`` of the truth there, and the nearest draw."""
    odo = drive_path(file, seed, course, vo_noise=vo_noise(course, vo_scale, vo_failures))
    truth = np.asarray(odo.trajectory.poses, np.float64)
    revisit = loops.find_revisit(truth, START_M, 0.5 * length_m)
    if revisit is None:
        return {"note": "no revisit within the radius in the driven path"}
    frame = approach_frame(truth, revisit, localmap_params(config).max_range)
    params = scaled(motion_params(config), noise_scale)
    if config.motion.noise_spread > 1:  # each draw its own factor, as the filter's particles
        params = scaled(params, particle_scales(draws, config.motion.noise_spread))
    pose = motion_draws(jax.random.key(seed), truth[0], odo.controls[:frame + 1],
                        odo.vo_draw.vo_failed[:frame + 1], params, draws)
    xy = np.asarray(pose[:, :2], np.float64)
    d = np.hypot(*(xy - truth[frame, :2]).T)
    mean, cov = xy.mean(0), np.cov(xy.T)  # the Gaussian fitted to the cloud
    vo = odo.vo_poses()[frame]
    p_best, k_best = best_scaled_within(mean, cov, truth[frame, :2], loops.TOLERANCE)
    return {"approach_frame": frame, "p_within": float(np.mean(d <= loops.TOLERANCE)),
            "p_gauss": gaussian_within(mean, cov, truth[frame, :2], loops.TOLERANCE),
            "p_best_scale": p_best, "best_scale": k_best,
            "spread_m": float(np.linalg.det(cov) ** 0.25),
            "nearest_m": float(d.min()), "draws": draws,
            "vo_miss_m": float(np.hypot(*(vo[:2] - truth[frame, :2])))}


def summarise(rows: list[dict], particles: list[int]) -> dict:
    """One loop's seeds (``loop_bound`` rows): the mean chance over them that one of J
    particles is within 1 m at the approach and the J at which it reaches ``SHARE``, from the
    count (``chance``), from the Gaussian fit (``chance_gauss``) and from the fit scaled per
    seed to suit the truth (``chance_best_scale``, ``best_scaled_within``); the medians of the
    cloud's spread and of the VO's miss there."""
    out = {"length_m": rows[0]["length_m"], "seeds": len(rows)}
    for field, suffix in (("p_within", ""), ("p_gauss", "_gauss"),
                          ("p_best_scale", "_best_scale")):
        p = np.asarray([r[field] for r in rows])
        out["chance" + suffix] = {J: float(np.mean(chance_of_one(p, J))) for J in particles}
        out["particles_for_share" + suffix] = particles_for(p)
    return {**out, "spread_m": float(np.median([r["spread_m"] for r in rows])),
            "vo_miss_median_m": float(np.median([r["vo_miss_m"] for r in rows]))}


def plot_bound(summary: dict, particles: list[int], path: Path) -> None:
    """The chance of a particle within 1 m at the approach against loop length, a colour per
    J: counted among the draws at the config's noise (solid) and with the best width per seed
    (``chance_best_scale``, dashed: no noise level gives more); circles with dots, the real
    paths' cuts with squares (unjoined: each cut is a loop of its own path, so their chances
    need not fall with length), and the share ``SHARE`` as a grey line."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    has_circles = any(name.startswith("circle-") for name in summary)
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for i, J in enumerate(particles):
        for family, marker in (("circle", "o"), ("cut", "s")):
            loops_ = sorted((s["length_m"], s) for name, s in summary.items()
                            if name.startswith("circle-") == (family == "circle"))
            if not loops_:
                continue
            x = [length for length, _ in loops_]
            for key, style, what in (("chance", "-", "at the noise given"),
                                     ("chance_best_scale", "--", "best width per seed")):
                ax.plot(x, [s[key][J] for _, s in loops_],
                        marker + (style if family == "circle" else ""), color=f"C{i}",
                        alpha=1.0 if key == "chance" else 0.6,
                        label=f"J={J}, {what}" if family == "circle" or not has_circles
                        else None)
    ax.axhline(SHARE, color="0.6", lw=0.8)
    ax.set_xscale("log")
    ax.set_ylim(-0.05, 1.05)
    ax.set_xlabel("loop length (m)")
    ax.set_ylabel("chance of a particle within 1 m at the approach")
    ax.set_title("flat-weight bound (circles: dots, real paths' cuts: squares)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--circles", type=float, nargs="*", default=[400, 800, 1000],
                    help="circle perimeters, m")
    ap.add_argument("--kitti", type=Path, nargs="*", default=[], help="KITTI pose files")
    ap.add_argument("--kitti-lengths", type=float, nargs="*", default=[1000],
                    help="loop lengths to cut from each KITTI file, m (the nearest found)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--draws", type=int, default=20000, help="motion-model paths per seed")
    ap.add_argument("--particles", type=int, nargs="+", default=[200, 2000],
                    help="the J to give the expected count and the chance of one for")
    ap.add_argument("--course", default="arroyo-a", help="world kind and VO noise")
    ap.add_argument("--config", type=Path, help="TOML config (configs/table1.toml: the "
                    "course's calibrated motion noise)")
    ap.add_argument("--set", action="append", default=[])
    add_vo_arguments(ap)
    ap.add_argument("--overlap", type=float, default=20.0, help="metres driven past the loop")
    ap.add_argument("--radius", type=float, default=2.0, help="revisit radius of KITTI cuts, m")
    ap.add_argument("--from-json", type=Path, nargs="*", default=[],
                    help="loop_closure --json files: their runs beside the prediction")
    ap.add_argument("--json", type=Path, help="write settings and every row here")
    ap.add_argument("--plot", type=Path, help="write the chance against loop length here (PNG)")
    args = ap.parse_args(argv)
    env = environment()
    print(f"# {env['date']} | {env['cpus']} cpus | jax {env['jax']}", flush=True)
    config = layered_config(args.config, args.course, args.set, courses=COURSES)
    print("# beyond a VO miss at the approach of "
          + ", ".join(f"{largest_miss(J):.1f} m (J={J})" for J in args.particles)
          + f" no noise level gives a seed a chance of {SHARE:.0%} of a particle within "
          f"{loops.TOLERANCE:g} m (largest_miss)", flush=True)
    filtered, runs = read_rows(args.from_json), {}
    for r in filtered:
        if r.get("closed") is not None and "approach_within_1m" in r:
            runs.setdefault((r["loop"], r["seed"]), []).append(r)
    rows, summary = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        todo = [circle_loop(Path(tmp), x, args.overlap) for x in args.circles]
        for file in args.kitti:
            todo += kitti_loops(Path(tmp), file, args.kitti_lengths, args.radius, args.overlap)
        for loop in todo:
            mine = []
            for seed in args.seeds:
                row = {"loop": loop.name, "length_m": loop.length_m, "seed": seed,
                       **loop_bound(loop.file, loop.length_m, seed, config, args.course,
                                    args.draws, args.vo_scale, args.noise_scale,
                                    args.vo_failures)}
                rows.append(row)
                if "p_within" not in row:
                    print(f"{loop.name:>18} seed {seed}: {row['note']}", flush=True)
                    continue
                mine.append(row)
                expect = ", ".join(f"J={J}: {J * row['p_within']:.2f} "
                                   f"({chance_of_one(row['p_within'], J):.0%})"
                                   for J in args.particles)
                seen = "; ".join(f"{r['proposal']} J={r['particles']}: "
                                 f"{r['approach_within_1m']} "
                                 f"{'closed' if r['closed'] else 'open'}"
                                 for r in runs.get((loop.name, seed), []))
                print(f"{loop.name:>18} seed {seed}: VO misses by {row['vo_miss_m']:6.2f} m, "
                      f"nearest of {args.draws} draws {row['nearest_m']:.2f} m; within 1 m "
                      f"expected (chance of one): {expect}"
                      + (f" | the filter's: {seen}" if seen else ""), flush=True)
            if mine:
                summary[loop.name] = s = summarise(mine, args.particles)
                print(f"  {loop.name}: the cloud's spread {s['spread_m']:.2f} m, the VO's miss "
                      f"{s['vo_miss_median_m']:.1f} m (medians); mean chance of a particle "
                      "within 1 m at the approach "
                      + ", ".join(f"J={J} {c:.0%}" for J, c in s["chance"].items())
                      + f"; J for {SHARE:.0%}: {s['particles_for_share']:.0f} (the draws "
                      f"counted); from the Gaussian fit "
                      + ", ".join(f"J={J} {c:.0%}" for J, c in s["chance_gauss"].items())
                      + f"; J for {SHARE:.0%}: {s['particles_for_share_gauss']:.0f}; the fit "
                      "with its width scaled per seed to suit the truth (the most any one "
                      "factor on the alphas gives) "
                      + ", ".join(f"J={J} {c:.0%}" for J, c in s["chance_best_scale"].items())
                      + f"; J for {SHARE:.0%}: {s['particles_for_share_best_scale']:.0f}",
                      flush=True)
    if args.plot and summary:
        plot_bound(summary, args.particles, args.plot)
    seen = against_runs(rows, filtered)
    for name, c in seen.items():
        print(f"  the filter's runs, {name} ({c['runs']}): predicted chance of a particle within "
              f"1 m at the approach {c['chance']:.0%}, had one {c['had_one']:.0%}; within 1 m "
              f"{c['expected']:.1f} predicted, {c['count']:.1f} had (means)", flush=True)
    if args.json:
        settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
        settings["kitti"] = [str(p) for p in args.kitti]
        settings["from_json"] = [str(p) for p in args.from_json]
        args.json.write_text(json.dumps({"settings": settings, "environment": env,
                                         "rows": rows, "summary": summary,
                                         "against_runs": seen}, indent=1,
                                        default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
