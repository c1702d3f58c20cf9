"""A small hand-built world for filter tests: a height-variance field with known truth.

The field is flat ground with a tiny spread plus Gaussian bumps of rough vegetation; points are
sampled in a disc around the true pose, with heights drawn from the field's local mean and
spread, and handed to the real local-map builder.
"""

from __future__ import annotations

import functools

import numpy as np

from gslam_jax.vo.localmap import LocalMapParams, build_local_maps
from gslam_jax.run import Run, integrate_controls


class World:
    def __init__(self, seed: int, half_size: float = 25.0, n_bumps: int = 120):
        rng = np.random.default_rng(seed)
        self.centres = rng.uniform(-half_size, half_size, (n_bumps, 2))
        self.radii = rng.uniform(0.3, 1.2, n_bumps)
        self.rough = rng.uniform(0.05, 0.4, n_bumps)

    def spread(self, xy: np.ndarray) -> np.ndarray:
        # x and y apart: no [N, bumps, 2] temporary; the same sums, so the same numbers
        d2 = ((xy[:, 0, None] - self.centres[:, 0]) ** 2
              + (xy[:, 1, None] - self.centres[:, 1]) ** 2)
        return 0.01 + (self.rough * np.exp(-0.5 * d2 / self.radii ** 2)).sum(-1)

    def observe(self, pose: np.ndarray, rng: np.random.Generator, n: int = 12000,
                max_range: float = 5.0) -> np.ndarray:
        """Robot-frame points around a world pose."""
        r = max_range * np.sqrt(rng.uniform(0, 1, n))
        a = rng.uniform(-np.pi, np.pi, n)
        local = np.column_stack([r * np.cos(a), r * np.sin(a)])
        c, s = np.cos(pose[2]), np.sin(pose[2])
        world = pose[:2] + local @ np.array([[c, s], [-s, c]])
        z = rng.normal(0.0, 1.0, n) * self.spread(world)
        return np.column_stack([local, z])


def truth_and_controls(kind: str = "loop", steps: int = 60, step_len: float = 0.5):
    """Ground-truth poses [T, 3] and exact robot-frame increments [T, 3]."""
    if kind == "loop":
        dtheta = 2 * np.pi / steps
        u = np.tile([step_len, 0.0, dtheta], (steps, 1))
    else:
        u = np.tile([step_len, 0.0, 0.0], (steps, 1))
    return integrate_controls(u), u


@functools.lru_cache(maxsize=2)
def _point_frames(seed: int, steps: int, kind: str) -> tuple[np.ndarray, ...]:
    """The robot-frame points of every frame of ``make_run``'s course (drawn once per process
    for runs that differ only in their local-map settings; read-only, as they are shared)."""
    world = World(seed)
    rng = np.random.default_rng(seed + 1)
    gt, _ = truth_and_controls(kind, steps)
    frames = tuple(world.observe(p, rng) for p in gt)
    for points in frames:
        points.flags.writeable = False
    return frames


def make_run(seed: int = 0, steps: int = 60, drift: float = 0.004, kind: str = "loop",
             params: LocalMapParams | None = None) -> tuple[Run, World]:
    """A Run whose VO has a heading bias of ``drift`` rad per step."""
    params = params or LocalMapParams(resolution=0.16, max_range=5.0, travel=1.0)
    world = World(seed)
    gt, u_true = truth_and_controls(kind, steps)
    u_vo = u_true + np.array([0.0, 0.0, drift])
    frames = _point_frames(seed, steps, kind)
    obs_index, maps, _, headings = build_local_maps(integrate_controls(u_vo), frames, params)
    run = Run(controls=u_vo, obs_index=obs_index, local_maps=maps, resolution=params.resolution,
              timestamps=np.arange(steps) * 0.2, ground_truth=gt,
              vo_failed=np.zeros(steps, bool), initial_pose=np.zeros(3),
              lattice_headings=None if params.lattice == "robot" else headings)
    return run, world
