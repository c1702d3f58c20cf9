"""Rendered-stereo simulator source (``--source sim-stereo``): images -> front-end -> Run.

A Table I course is driven through its procedural world exactly as in ``datasets.sim`` (same
seed, same ground truth); at every ground-truth pose ``sim.render.StereoRenderer`` draws both
stereo pairs, and the real OpenCV front-end (``vo.frontend.run_frontend``) does the rest: VO on
pair 0, dense SGBM disparity on both pairs -> points -> local maps fused at the VO poses. Nothing
but the images reaches the front-end; ground truth is attached only for scoring.

The config's [rig] ``height`` and ``pitch`` move the rendered cameras (``rig_render_params``):
the images are drawn from the mount the front-end is then given, so a pitched rig is rendered
and assumed alike. The renderer draws two pairs yawed +-35 degrees at the robot's centre
without roll, so the other [rig] keys are refused.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from gslam_jax.config import Config, ConfigError
from gslam_jax.datasets.mount import camera_mount, mount_values
from gslam_jax.datasets.registry import DataSource, LoadedSource, Source, stereo_settings
from gslam_jax.datasets.sim import Odometry, ProgressFn, simulate_odometry
from gslam_jax.run import Run
from gslam_jax.sim.environments import world_for_course
from gslam_jax.sim.render import RenderParams, StereoRenderer, camera_mounts
from gslam_jax.sim.world import World
from gslam_jax.vo.frontend import FrontEndParams, FrontEndSummary, run_frontend
from gslam_jax.vo.localmap import LocalMapParams, localmap_params

__all__ = ["SimStereoParams", "SimStereoInfo", "load_sim_stereo", "rig_render_params"]

RENDERED_RIG_KEYS = ("height", "pitch")  # the [rig] keys the renderer can draw


@dataclass(frozen=True)
class SimStereoParams:
    """Renderer and front-end settings; ``frontend.local_map`` is replaced by the caller's."""

    render: RenderParams = field(default_factory=RenderParams)
    frontend: FrontEndParams = field(default_factory=FrontEndParams)
    vo_pair: int = 0  # 0: the left-looking pair, 1: the right-looking one


@dataclass
class SimStereoInfo:
    """What the rendered run knows besides the Run: truth, front-end summary and timings."""

    odometry: Odometry
    world: World
    summary: FrontEndSummary
    vo_poses: np.ndarray  # [T, 4, 4] front-end robot poses
    inliers: np.ndarray  # [T] VO inliers per frame
    timings: dict[str, float]

    def text(self) -> str:
        t = self.timings
        return (f"{self.summary.text()}\nmean VO inliers {np.mean(self.inliers[1:]):.0f}; "
                f"render {t['render_s']:.1f} s, front-end {t['frontend_s']:.1f} s "
                f"({1e3 * t['frontend_s'] / max(self.summary.frames, 1):.0f} ms/frame)")


def load_sim_stereo(course: str, seed: int = 0, local_map_params: LocalMapParams | None = None,
                    max_frames: int | None = None, progress: ProgressFn | None = None,
                    params: SimStereoParams = SimStereoParams()) -> tuple[Run, SimStereoInfo]:
    """Render ``course`` (seeded like ``simulate_run``) and run the stereo front-end on it.

    Returns the Run (VO controls, local maps from both pairs, ground truth) and the info.
    ``max_frames`` truncates the course; ``progress(done, total)`` is called every few frames.
    """
    if params.vo_pair not in (0, 1):
        raise ValueError(f"vo_pair must be 0 or 1, got {params.vo_pair}")
    t0 = time.perf_counter()
    odo = simulate_odometry(course, seed, max_frames=max_frames)
    world = world_for_course(odo.course, seed)
    renderer = StereoRenderer(world, params.render, seed)
    gt = odo.trajectory.poses
    T = len(gt)
    other = 1 - params.vo_pair
    cache: dict[int, list] = {}
    timings = {"world_s": time.perf_counter() - t0, "render_s": 0.0}
    every = max(T // 100, 1)

    def frame(t: int) -> list:
        if t not in cache:
            cache.clear()
            r0 = time.perf_counter()
            cache[t] = renderer.render_frame(gt[t], t)
            timings["render_s"] += time.perf_counter() - r0
            if progress is not None and (t % every == 0 or t == T - 1):
                progress(t + 1, T)
        return cache[t]

    def load(t: int) -> tuple[np.ndarray, np.ndarray]:
        return frame(t)[params.vo_pair]

    def extra(t: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        left, right = frame(t)[other]
        return [(left, right, renderer.mounts[other][0])]

    fe_params = params.frontend
    if local_map_params is not None:
        from dataclasses import replace
        fe_params = replace(fe_params, local_map=local_map_params)
    t1 = time.perf_counter()
    res = run_frontend(load, T, renderer.rig, renderer.mounts[params.vo_pair][0],
                       odo.trajectory.timestamps, fe_params, ground_truth=gt.copy(),
                       initial_pose=gt[0].copy(), source=f"sim-stereo {course} seed {seed}",
                       extra_pairs=extra)
    timings["frontend_s"] = time.perf_counter() - t1 - timings["render_s"]
    timings["total_s"] = time.perf_counter() - t0
    info = SimStereoInfo(odo, world, res.summary, res.poses,
                         np.array([r.n_inliers for r in res.vo]), timings)
    return res.run, info


def rig_render_params(config: Config, render: RenderParams,
                      where: str = "--source sim-stereo") -> RenderParams:
    """``render`` with the cameras' height and pitch of the config's [rig] (the renderer's
    pair-0 left camera through ``datasets.mount.camera_mount``); ConfigError naming the other
    [rig] keys, which the renderer cannot draw."""
    rig = config.rig
    if rig.is_default():
        return render
    refused = [k for k in rig.given() if k not in RENDERED_RIG_KEYS]
    if refused:
        raise ConfigError(f"{where}: [rig] {', '.join(refused)}: the renderer draws two pairs "
                          "yawed +-35 deg at the robot's centre, without roll; only [rig] "
                          f"{' and '.join(RENDERED_RIG_KEYS)} apply")
    values = mount_values(camera_mount(config, camera_mounts(render)[0][0], where))
    return replace(render, camera_height=values["height"],
                   camera_pitch=float(np.deg2rad(values["pitch"])))


def _load(src: Source, config: Config, progress: ProgressFn | None = None) -> LoadedSource:
    sp = SimStereoParams()
    sp = replace(sp, render=rig_render_params(config, sp.render),
                 frontend=replace(sp.frontend,
                                  stereo=stereo_settings(config, sp.frontend.stereo)))
    run, info = load_sim_stereo(src.course, src.sim_seed, localmap_params(config, "stereo"),
                                max_frames=src.max_frames, progress=progress, params=sp)
    print(info.text())
    return LoadedSource(run, f"rendered stereo of course {src.course} (seed {src.sim_seed})")


SOURCE = DataSource(name="sim-stereo", help="rendered stereo images of a simulated course "
                    "through the OpenCV front-end", load=_load, simulated=True, images=True)
