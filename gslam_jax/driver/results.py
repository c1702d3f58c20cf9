"""What ``run_slam`` returns (``SlamResult``, its trajectories built from the particles'
ancestry on first use: ``PathEstimates``) and hands its ``on_chunk`` callback after each chunk
of frames (``ChunkReport``)."""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gslam_jax import rbpf
from gslam_jax.driver.observations import local_map_footprints
from gslam_jax.gridmap import GridMap, turn_poses
from gslam_jax.run import Run

__all__ = ["PathEstimates", "SlamResult", "ChunkReport"]

ANCESTRY_PATHS = ("best", "map", "smoothed", "steps", "mode", "mode_mean", "local_steps")


class Ancestry(NamedTuple):
    """A whole run's particle history, what ``PathEstimates`` builds the paths from."""

    pose: np.ndarray       # [T, J, 3] the particles' poses after each frame (map lattice's axes)
    ancestors: np.ndarray  # [T, J] each particle's parent slot at each frame
    log_w: jax.Array       # [J] final log weights
    best: jax.Array        # [] final highest-weight slot
    map_slot: jax.Array    # [] the slot whose map the run reports (``rbpf.map_particle``)
    step_log_w: np.ndarray  # [T, J] log weights after each frame (``rbpf.step_history``)
    resampled: np.ndarray   # [T] bool
    mean_pose: np.ndarray   # [T, 3] weighted mean per frame
    run: Run                # the run filtered (on the map lattice's axes): its footprints
    heading: float          # the map lattice's axes in the run's frame


class PathEstimates:
    """The run's trajectories through the particles' ancestry, in the run's frame: "best" (the
    final best particle's, ``rbpf.backtrack_path``), "map" (the particle whose map the run
    reports), "smoothed" (``rbpf.smoothed_mean_path``), "steps" (``rbpf.smoothed_step_path``),
    "mode" (the final densest particle's), "mode_mean" (``rbpf.mode_mean_path``) and
    "local_steps" (``rbpf.local_step_path``). Each is built on first use and kept;
    ``PathEstimates.given`` holds paths computed elsewhere (None: not given)."""

    def __init__(self, ancestry: Ancestry | None = None,
                 given: dict[str, np.ndarray | None] | None = None):
        unknown = set(given or ()) - set(ANCESTRY_PATHS)
        if unknown:
            raise ValueError(f"unknown path estimates {sorted(unknown)}; the estimates are "
                             f"{', '.join(ANCESTRY_PATHS)}")
        self._ancestry = ancestry
        self._paths: dict[str, np.ndarray | None] = dict(given or {})
        self._densest: jax.Array | None = None

    @classmethod
    def given(cls, **paths: np.ndarray | None) -> PathEstimates:
        """Paths [T, 3] by name (``ANCESTRY_PATHS``), e.g. for a result made without the filter."""
        return cls(None, paths)

    def __getitem__(self, name: str) -> np.ndarray | None:
        if name not in ANCESTRY_PATHS:
            raise KeyError(f"no path estimate {name!r}; the estimates are "
                           f"{', '.join(ANCESTRY_PATHS)}")
        if name not in self._paths:
            a = self._ancestry
            self._paths[name] = None if a is None else \
                turn_poses(np.asarray(self._build(name, a)), a.heading)
        return self._paths[name]

    def _build(self, name: str, a: Ancestry) -> jax.Array:
        poses, ancestors = jnp.asarray(a.pose), jnp.asarray(a.ancestors)
        builders: dict[str, Callable[[], jax.Array]] = {
            "best": lambda: rbpf.backtrack_path(poses, ancestors, a.best),
            "map": lambda: rbpf.backtrack_path(poses, ancestors, a.map_slot),
            "smoothed": lambda: rbpf.smoothed_mean_path(poses, ancestors, a.log_w),
            "steps": lambda: rbpf.smoothed_step_path(poses, ancestors, a.log_w),
            "mode": lambda: rbpf.backtrack_path(poses, ancestors, self._densest_slot(poses)),
            "mode_mean": lambda: rbpf.mode_mean_path(poses, ancestors, a.log_w,
                                                     self._densest_slot(poses)),
            "local_steps": lambda: rbpf.ancestry_path(
                "local_steps", poses, ancestors, a.log_w, a.best,
                rbpf.step_history(a.step_log_w, a.resampled, a.mean_pose,
                                  local_map_footprints(a.run))),
        }
        return builders[name]()

    def _densest_slot(self, poses: jax.Array) -> jax.Array:
        """The final densest particle (``rbpf.densest_particle``), once for both mode paths."""
        if self._densest is None:
            self._densest = rbpf.densest_particle(poses[-1], self._ancestry.log_w)
        return self._densest


class SlamResult(NamedTuple):
    """Host-side (NumPy) outputs of one Gamma-SLAM run. The trajectories through the
    particles' ancestry (``best_path`` ... ``local_steps_path``) are ``paths``', built when
    first read."""

    paths: PathEstimates       # the ancestry's trajectories (the properties below)
    best_pose: np.ndarray      # [T, 3] highest-weight particle per frame
    mean_pose: np.ndarray      # [T, 3] weighted mean per frame
    vo_path: np.ndarray        # [T, 3] VO-only trajectory
    ess: np.ndarray            # [T]
    resampled: np.ndarray      # [T] bool
    updated: np.ndarray        # [T] bool
    log_lik: np.ndarray        # [T] log mean weight increments
    exponent: np.ndarray       # [T] tempering exponent of each update (1: the paper's beta)
    kmap: np.ndarray           # [H, W] the map of ``map_path``'s particle (``rbpf.map_particle``)
    smap: np.ndarray           # [H, W]
    map_origin: tuple[float, float]  # in the lattice's axes (``GridMap``)
    resolution: float
    extent_violations: int     # particle-updates with observed cells off the map
    empty_observations: int    # local maps with no informative cell
    seconds: float             # filter wall time after compilation
    compile_seconds: float
    store: str = "dense"       # the map store the filter ran on ([map] store, "auto" resolved)
    map_bytes: int = 0         # bytes the map store allocates (dense maps, or the tile pool)
    map_peak_bytes: int = 0    # most bytes the maps held at once (shared: live tiles + tables)
    estimate: str = "best"     # [filter] estimate: which trajectory ``path`` is
    compile_frames: int = 0    # frames run in the first chunk, timed with the compilation
    map_heading: float = 0.0   # radians: the map lattice's axes in the run's frame ([map] axes)
    noise_scale: np.ndarray | None = None  # [T] the particles' factor on the motion stds after
    #                                        each frame, weighted geometric mean (all 1 unless
    #                                        [motion] noise_spread > 1)

    @property
    def best_path(self) -> np.ndarray:
        """[T, 3] the final best particle's path through its ancestry."""
        return self.paths["best"]

    @property
    def map_path(self) -> np.ndarray:
        """[T, 3] the path of the particle whose map ``kmap`` is (``rbpf.map_particle``):
        ``mode_path`` under estimate "mode" or "mode_mean", else ``best_path``."""
        return self.paths["map"]

    @property
    def smoothed_path(self) -> np.ndarray:
        """[T, 3] final-weighted mean of every final particle's ancestry."""
        return self.paths["smoothed"]

    @property
    def steps_path(self) -> np.ndarray | None:
        """[T, 3] the smoother's mean steps, composed."""
        return self.paths["steps"]

    @property
    def mode_path(self) -> np.ndarray | None:
        """[T, 3] the final densest particle's ancestral path."""
        return self.paths["mode"]

    @property
    def mode_mean_path(self) -> np.ndarray | None:
        """[T, 3] the smoother's mean over the densest particle's 1 m neighbourhood
        (``rbpf.mode_mean_path``)."""
        return self.paths["mode_mean"]

    @property
    def local_steps_path(self) -> np.ndarray | None:
        """[T, 3] mean steps, each weighed by the factors that bear on it
        (``rbpf.local_step_path``)."""
        return self.paths["local_steps"]

    @property
    def path(self) -> np.ndarray:
        """[T, 3] the reported trajectory ([filter] estimate): ``best_path``, ``mean_pose``,
        ``smoothed_path``, ``steps_path``, ``mode_path``, ``mode_mean_path`` or
        ``local_steps_path``."""
        if self.estimate == "mean":
            return self.mean_pose
        return self.paths[self.estimate]

    @property
    def grid(self) -> GridMap:
        """The run's map (``kmap``, ``smap``: ``map_path``'s particle's) as a ``GridMap``
        (float64), e.g. for ``align_maps``."""
        return GridMap(np.asarray(self.kmap, np.float64), np.asarray(self.smap, np.float64),
                       tuple(self.map_origin), float(self.resolution), float(self.map_heading))


class ChunkReport(NamedTuple):
    """What ``run_slam`` hands its ``on_chunk`` callback after each chunk of frames: host
    values, except ``state``, which is donated to the next chunk's scan (use it within the
    call, e.g. ``rbpf.particle_map(state, int(state.best), cfg)`` for the best map so far)."""

    run: Run                 # the run being filtered (rebased onto a prior map's start), on
    #                          the map lattice's axes, as are the poses and maps below
    start: int               # the chunk's first frame
    info: rbpf.StepInfo      # per frame of the chunk: particle poses [n, J, 3], ess [n], ...
    best_pose: np.ndarray    # [n, 3] highest-weight particle per frame
    mean_pose: np.ndarray    # [n, 3] weighted mean per frame
    state: rbpf.FilterState  # after the chunk's last frame
    cfg: rbpf.FilterConfig
    heading: float = 0.0     # the map lattice's axes in the run's frame: ``turn_poses(x,
    #                          heading)`` carries the poses above into it
