"""Simulator adapter: a Table I course driven through a procedural world, as a ``Run``.

Pipeline: course (seeded path) -> world around it -> ground-truth poses at the frame rate ->
VO increments with known noise -> point sensor at the *true* poses -> local maps fused at the *VO*
poses (as the robot does in reality) -> ``Run`` with ground truth, plus ``SimInfo`` with what was
drawn. Random streams are independent per stage and derived from ``seed`` alone, so a run is
reproducible, and e.g. changing the sensor does not change the world or the VO noise.
``drive_course`` (truth and VO) and ``sense_run`` (sensor and local maps) are the two halves every
simulated source shares; only the course and the world differ between sources.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace
from typing import Callable, Iterator, NamedTuple

import numpy as np

from gslam_jax.config import Config
from gslam_jax.datasets.registry import DataSource, LoadedSource, Source
from gslam_jax.errors import ArgumentError, integer_argument
from gslam_jax.run import Run, integrate_controls
from gslam_jax.sim.courses import COURSES, Course, make_course
from gslam_jax.sim.environments import world_for_course
from gslam_jax.sim.sensor import PointSensor, SensorParams
from gslam_jax.sim.trajectory import DriveParams, Trajectory, drive
from gslam_jax.sim.vonoise import (VO_PROFILES, VONoiseDraw, VONoiseParams, apply_vo_noise,
                                   true_increments)
from gslam_jax.sim.world import World
from gslam_jax.vo.localmap import LocalMapParams, build_local_maps, localmap_params

__all__ = ["SimInfo", "Odometry", "drive_course", "simulate_odometry", "sense_run",
           "simulate_run", "course_names", "ProgressFn"]

ProgressFn = Callable[[int, int], None]
"""Called as progress(frames_done, frames_total) while the sensor runs."""


@dataclass
class SimInfo:
    """Everything a simulated run knows that the filter must not see.

    vo_noise: the true VO noise parameters (alphas of eqs. 1-3 and the bias/failure model).
    survey_frames: frames at which the robot stood at a survey point (start and end included).
    survey_points: [S, 2] true positions at those frames.
    """

    course: Course
    world: World
    trajectory: Trajectory
    vo_noise: VONoiseParams
    vo_draw: VONoiseDraw
    sensor: SensorParams
    localmap: LocalMapParams
    survey_frames: np.ndarray
    survey_points: np.ndarray
    points_per_frame: float
    dropped_points: int
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return self.course.spec.name

    def summary(self) -> dict:
        """JSON-ready record of the simulation (for a results directory's config/metrics)."""
        return {
            "course": self.course.spec.name, "description": self.course.spec.description,
            "seed": self.course.seed, "world_kind": self.world.kind,
            "world_fingerprint": self.world.fingerprint(),
            "course_length_m": round(self.course.length, 3),
            "frames": int(self.trajectory.num_frames),
            "rate_hz": (float(1.0 / np.median(np.diff(self.trajectory.timestamps)))
                        if self.trajectory.num_frames > 1 else None),  # one frame has no rate
            "vo_noise": asdict(self.vo_noise),
            "vo_failed_frames": int(self.vo_draw.vo_failed.sum()),
            "sensor": asdict(self.sensor),
            "survey_frames": self.survey_frames.tolist(),
            "points_per_frame": round(self.points_per_frame, 1),
            "points_outside_local_maps": self.dropped_points,
            "timings_s": {k: round(v, 3) for k, v in self.timings.items()},
        }


def course_names() -> list[str]:
    """Valid course names for ``simulate_run``."""
    return list(COURSES)


def _stream(seed: int, stage: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(seed), 0x5151, stage]))


class Odometry(NamedTuple):
    """The cheap half of a simulation (no world, no sensor): course, truth and VO."""

    course: Course
    trajectory: Trajectory
    controls: np.ndarray  # [T, 3] VO increments
    vo_draw: VONoiseDraw
    vo_noise: VONoiseParams

    def vo_poses(self) -> np.ndarray:
        return integrate_controls(self.controls, self.trajectory.poses[0])


def drive_course(crs: Course, seed: int, noise: VONoiseParams, *,
                 drive_params: DriveParams | None = None,
                 max_frames: int | None = None) -> Odometry:
    """Drive ``crs`` (ground truth at the frame rate) and draw its VO increments with ``noise``
    from the stream of ``seed``: the odometry half of every simulated source."""
    if max_frames is not None and max_frames < 1:
        raise ValueError(f"max_frames must be >= 1 or None, got {max_frames}")
    traj = drive(crs, drive_params)
    # Noise is drawn for the whole course, then cut: a truncated run is a prefix of the full one.
    controls, draw = apply_vo_noise(true_increments(traj.poses), noise, _stream(seed, 1))
    if max_frames is not None and max_frames < traj.num_frames:
        n = max_frames
        traj = Trajectory(traj.timestamps[:n], traj.poses[:n], traj.s[:n],
                          traj.survey_frames[traj.survey_frames < n])
        controls = controls[:n]
        draw = replace(draw, scale_bias=draw.scale_bias[:n], heading_bias=draw.heading_bias[:n],
                       vo_failed=draw.vo_failed[:n])
    return Odometry(crs, traj, controls, draw, noise)


def simulate_odometry(course: str, seed: int = 0, *, drive_params: DriveParams | None = None,
                      vo_noise: VONoiseParams | None = None, max_frames: int | None = None,
                      noise_seed: int | None = None) -> Odometry:
    """Course, ground truth and VO increments exactly as ``simulate_run`` draws them (same seeds,
    same numbers), without the world and the sensor: for VO-only statistics in milliseconds."""
    if course not in COURSES:
        raise ValueError(f"unknown course {course!r}; valid courses: {', '.join(COURSES)}")
    noise = vo_noise or VO_PROFILES[course]
    return drive_course(make_course(course, seed), seed if noise_seed is None else noise_seed,
                        noise, drive_params=drive_params, max_frames=max_frames)


def simulate_run(course: str, seed: int = 0, params: LocalMapParams | None = None, *,
                 sensor: SensorParams | None = None, drive_params: DriveParams | None = None,
                 vo_noise: VONoiseParams | None = None, max_frames: int | None = None,
                 progress: ProgressFn | None = None,
                 noise_seed: int | None = None) -> tuple[Run, SimInfo]:
    """Simulate ``course`` (one of ``course_names()``) with ``seed``.

    noise_seed: draw the VO and sensor noise from this seed instead (the path and the world
        stay those of ``seed``): the same terrain driven again, e.g. for map merging.
    params: local-map settings (its resolution is the Run's); defaults to ``LocalMapParams()``.
    vo_noise: defaults to the course's profile in ``VO_PROFILES``.
    max_frames: truncate the course (for quick tests); None drives all of it.
    progress: optional callback ``progress(done, total)`` called every few frames.
    An ArgumentError names an unknown course, a seed outside [0, 2^32) or a max_frames that is not a positive
    integer (``errors.integer_argument``).
    """
    if not isinstance(course, str) or course not in COURSES:
        raise ArgumentError(f"simulate_run: course must be one of {', '.join(COURSES)}, got "
                            f"{course!r:.40}")
    for name, value in (("seed", seed), ("noise_seed", noise_seed)):
        if value is not None:
            integer_argument(value, f"simulate_run: {name}", 0, 2 ** 32,
                             bounds="an integer in [0, 2^32)")
    if max_frames is not None:
        integer_argument(max_frames, "simulate_run: max_frames", 1,
                         bounds="a positive integer (None: the whole course)")
    params = params or LocalMapParams()
    t0 = time.perf_counter()
    odo = simulate_odometry(course, seed, drive_params=drive_params, vo_noise=vo_noise,
                            max_frames=max_frames, noise_seed=noise_seed)
    world = world_for_course(odo.course, seed)
    timings = {"world_s": time.perf_counter() - t0}
    return sense_run(odo, world, seed if noise_seed is None else noise_seed, params, sensor,
                     progress=progress, timings=timings, t0=t0)


def sense_run(odo: Odometry, world: World, seed: int, params: LocalMapParams,
              sensor: SensorParams | None = None, *, progress: ProgressFn | None = None,
              timings: dict[str, float] | None = None,
              t0: float | None = None) -> tuple[Run, SimInfo]:
    """The sensing half of every simulated source: the point sensor at the true poses of ``odo``
    in ``world`` (its stream drawn from ``seed``), local maps fused at the VO poses, and the
    ``Run`` with its ``SimInfo``. ``sensor`` defaults to ``params``' range; ``timings`` (e.g.
    the world's) gain the sensing time and the total since ``t0``."""
    sensor_params = sensor or SensorParams(max_range=params.max_range)
    timings = {} if timings is None else timings
    t0 = time.perf_counter() if t0 is None else t0
    crs, traj, controls, draw, noise = odo
    gt = traj.poses
    T = gt.shape[0]
    vo_poses = odo.vo_poses()

    point_sensor = PointSensor(world, sensor_params)
    rng_sensor = _stream(seed, 2)
    counts = np.zeros(T, np.int64)
    every = max(T // 100, 1)

    def frames() -> Iterator[np.ndarray]:
        for t in range(T):
            pts = point_sensor.observe(gt[t], rng_sensor)
            counts[t] = len(pts)
            if progress is not None and (t % every == 0 or t == T - 1):
                progress(t + 1, T)
            yield pts

    t1 = time.perf_counter()
    obs_index, local_maps, dropped, lattice_headings = build_local_maps(vo_poses, frames(),
                                                                         params, gt[0])
    timings["sensor_and_maps_s"] = time.perf_counter() - t1
    timings["total_s"] = time.perf_counter() - t0

    run = Run(controls=controls, obs_index=obs_index, local_maps=local_maps,
              resolution=float(params.resolution), timestamps=traj.timestamps.copy(),
              ground_truth=gt.copy(), vo_failed=draw.vo_failed.copy(),
              initial_pose=gt[0].copy(), sensor="points",
              lattice_headings=None if params.lattice == "robot" else lattice_headings)
    info = SimInfo(course=crs, world=world, trajectory=traj, vo_noise=noise, vo_draw=draw,
                   sensor=sensor_params, localmap=params, survey_frames=traj.survey_frames,
                   survey_points=gt[traj.survey_frames, :2].copy(),
                   points_per_frame=float(counts.mean()), dropped_points=int(dropped),
                   timings=timings)
    return run, info


def _load(src: Source, config: Config, progress: ProgressFn | None = None) -> LoadedSource:
    run, info = simulate_run(src.course, seed=src.sim_seed, params=localmap_params(config),
                             max_frames=src.max_frames, progress=progress,
                             noise_seed=src.noise_seed)
    noise = "" if src.noise_seed is None else f", noise seed {src.noise_seed}"
    return LoadedSource(run, f"simulated course {src.course} (seed {src.sim_seed}{noise})", info)


SOURCE = DataSource(name="sim", help="simulated course (point sensor, VO noise drawn by the "
                    "course's profile)", load=_load, simulated=True, noise_seed=True)
