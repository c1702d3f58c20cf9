"""Gamma-SLAM on a live robot: frames pushed one at a time, the estimate after each.

``Online`` drives the same kernel as ``slam.run_slam`` (``rbpf.scan_frames`` over one frame,
``observations.refine_observations``, ``sizing.filter_params``,
``sizing.extent_filter_config``), one jitted call per frame, compiled at the first frame and
never again: every frame has the same shapes (a frame without a local map carries a zero one
and is not updated). Frame t's PRNG key is ``fold_in(key, t)``, which under JAX's partitionable
threefry (the default) is ``rbpf.frame_keys(key, T)[t]``: on the same frames, the same seed and
the same map, the poses are the batch run's. With ``[filter] range_noise = "profile"`` the
profile is a running estimate from the maps pushed so far (``observations.RunningRangeNoise``;
the batch run's is from the whole run), so there the two differ.

A live robot has no path yet, so the map cannot be sized from it: its extent is given (a
``sizing.MapExtent``, or the side in metres of the square the robot drives in, centred on the
start). The map does not grow (a larger map would be a new shape, hence a recompilation):
when a local map reaches past its edge the frame is applied with the cells beyond the edge
skipped, as the batch run does, and ``MapEdgeError`` is raised.

Arguments are checked as the command line checks its options: a wrong type, shape or value
is an ``ArgumentError`` (``errors``) naming the argument, and a malformed frame (non-finite or
impossible local-map statistics: ``run.checks.check_statistics``, as a Run file's) an
``InputError`` naming the frame and cell, before the filter sees it.
"""

from __future__ import annotations

import math
import time
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gslam_jax import choices, rbpf
from gslam_jax.config import Config, ConfigError
from gslam_jax.driver import chunk_checks, observations, sizing
from gslam_jax.errors import (ArgumentError, InputError, array_argument, integer_argument,
                              number_argument)
from gslam_jax.gridmap import GridMap, turn_poses
from gslam_jax.rbpf import cells, maps
from gslam_jax.run import integrate_controls
from gslam_jax.run.checks import check_statistics, coordinate_limit
from gslam_jax.vo.localmap import LocalMapBuilder, localmap_params, map_axes_heading

__all__ = ["Online", "OnlineFrame", "OnlineStats", "Particles", "MapEdgeError",
           "DEFAULT_SIZE", "online_step"]

DEFAULT_SIZE = 100.0  # metres: side of the square the robot drives in when no extent is given


class MapEdgeError(InputError):
    """A local map reached past the edge of the live map's fixed extent."""


class OnlineFrame(NamedTuple):
    """The estimate after one pushed frame (host values)."""

    pose: np.ndarray   # [3] the highest-weight particle's pose (x, y, theta)
    mean: np.ndarray   # [3] the weighted mean pose (circular mean heading)
    ess: float         # effective sample size after the frame's update (J without one)
    updated: bool      # the frame carried a local map
    resampled: bool
    seconds: float     # wall time of this push (the first includes the compilation)


class Particles(NamedTuple):
    pose: np.ndarray    # [J, 3]
    weight: np.ndarray  # [J] normalised weights
    noise_scale: np.ndarray | None = None  # [J] each particle's factor on the motion stds
    #                                        ([motion] noise_spread > 1; else None: all 1)


class OnlineStats(NamedTuple):
    """Timing of the frames pushed so far. ``realtime_factor``: seconds of log (the span of the
    pushed times after the first frame) per second of filter compute over those frames (the
    first, which compiles, excluded); > 1 keeps up with the robot. NaN until two frames."""

    frames: int
    updates: int
    compile_seconds: float      # the first push (compilation included)
    seconds: float              # every later push
    log_seconds: float
    realtime_factor: float
    frame_latency: np.ndarray   # [frames - 1] seconds per push after the first
    update_latency: np.ndarray  # [updates after the first frame] seconds of pushes with a map


@partial(jax.jit, static_argnames=("cfg",), donate_argnums=(0,))
def online_step(state: rbpf.FilterState, key: jax.Array, t: jax.Array, control: jax.Array,
                raw_obs: jax.Array, has_obs: jax.Array, lattice_heading: jax.Array,
                fallback: jax.Array, settings: observations.ObsSettings,
                params: rbpf.FilterParams, cfg: rbpf.FilterConfig
                ) -> tuple[rbpf.FilterState, tuple[rbpf.StepInfo, jax.Array, jax.Array]]:
    """One frame t of the batch run's scan: its key ``fold_in(key, t)``, its raw observation
    [L, L, 2] refined (``observations.refine_observations``) and, where ``has_obs``, the update
    (the local map on a lattice turned by ``lattice_heading``, ``Run.lattice_headings``); the
    motion noise ``[motion] fallback_scale`` times the VO's where ``fallback``.
    ``state`` is donated. Returns the state and the frame's (StepInfo, best pose, mean pose)."""
    keys = jax.random.fold_in(key, t)[None]
    obs = observations.refine_observations(raw_obs[None], settings)
    index = jnp.where(has_obs, 0, -1).astype(jnp.int32)[None]
    state, out = rbpf.scan_frames(state, keys, control[None], index, obs, params, cfg,
                                  lattice_heading[None], fallback[None])
    return state, jax.tree.map(lambda x: x[0], out)


def _real(value) -> np.ndarray | None:
    """``value`` as a float64 array when it holds real numbers, else None."""
    try:
        array = np.asarray(value)
    except (TypeError, ValueError):  # ragged nested lists
        return None
    return array.astype(np.float64) if array.dtype.kind in "iuf" else None


def _check_arguments(config, map_extent, seed, local_size, observed_cells, sensor,
                     filter_config) -> None:
    """ArgumentError naming the first of ``Online``'s arguments of the wrong type or range."""
    if not isinstance(config, Config):
        raise ArgumentError(f"Online: config must be a gslam_jax.Config (Config(), or "
                            f"gslam_jax.load_config(path)), got {type(config).__name__}")
    if seed is not None:
        integer_argument(seed, "Online: seed", 0, 2 ** 32, bounds="an integer in [0, 2^32)")
    if local_size is not None:
        integer_argument(local_size, "Online: local_size", 1)
    integer_argument(observed_cells, "Online: observed_cells", 0,
                     bounds="an integer >= 0 (0: no cap)")
    if sensor is not None and sensor not in choices.SENSORS:
        raise ArgumentError(f"Online: sensor must be one of {', '.join(choices.SENSORS)} or "
                            f"None, got {sensor!r:.40}")
    if filter_config is not None and not isinstance(filter_config, rbpf.FilterConfig):
        raise ArgumentError(f"Online: filter_config must be an rbpf.FilterConfig, got "
                            f"{type(filter_config).__name__}")
    what = ("a side in metres, or a sizing.MapExtent / (origin, shape) pair: origin 2 finite "
            "numbers (metres), shape 2 positive integers (cells)")
    if map_extent is None or (isinstance(map_extent, (int, float)) and
                              not isinstance(map_extent, bool)):
        return
    if not isinstance(map_extent, (tuple, list)) or len(map_extent) != 2:
        raise ArgumentError(f"Online: map_extent must be {what}, got {map_extent!r:.80}")
    origin, shape = map_extent
    origin_ok = _real(origin)
    if origin_ok is None or origin_ok.shape != (2,) or not np.isfinite(origin_ok).all() or \
            not isinstance(shape, (tuple, list)) or len(shape) != 2:
        raise ArgumentError(f"Online: map_extent must be {what}, got {map_extent!r:.80}")
    for n in shape:
        integer_argument(n, "Online: map_extent's shape", 1, bounds="2 positive integers")


def _extent(config: Config, size: float, start: np.ndarray, local_size: int) -> sizing.MapExtent:
    """The map around the square of side ``size`` metres centred on ``start`` (plus a local
    map's reach), sized by the batch run's rule (``sizing.map_extent``)."""
    if not (math.isfinite(size) and size >= 0):
        raise ConfigError(f"Online: map_extent must be a size >= 0 metres, got {size}")
    probe = rbpf.FilterConfig(num_particles=1, map_shape=(8, 8), map_origin=(0.0, 0.0),
                              resolution=config.map.resolution, local_size=local_size,
                              unknown_cells=config.filter.unknown_cells)
    return sizing.map_extent(start[None], local_size, config.map.resolution, 0.5 * size,
                           probe.window)


class Online:
    """Gamma-SLAM one frame at a time (see the module docstring).

    config: the run's settings ([filter], [motion], [map], [localmap]).
    map_extent: ``sizing.MapExtent`` (origin, shape in cells, on the map's axes), or a float:
        the side in metres of the square centred on ``start_pose`` the robot may drive in;
        None: ``DEFAULT_SIZE``.
    start_pose: [3] the pose before the first frame (zeros: the robot's own frame). With
        ``[map] axes = "start"`` the map lies on the robot's axes there (``heading``, its
        angle in the frame) and the filter runs on them, as ``gslam run``'s; the poses, paths
        and particles given back are in the frame, the map (``GridMap.heading``) on its axes.
    seed: the filter's seed (None: [filter] seed); the batch run with that seed draws the same.
    local_size: side L of the local maps pushed (None: from [localmap], ``localmap_params``).
    observed_cells: the cap M on informative cells per local map (0: L*L, no cap).
    sensor: how the pushed local maps are made, one of ``choices.SENSORS`` ("stereo" for a
        stereo rig's dense points), for the automatic ``[filter] ess_target``; None: "points".
    filter_config: a ready ``rbpf.FilterConfig`` instead of the five above (e.g. a batch run's,
        ``slam.run_filter_config``, to reproduce it).
    """

    def __init__(self, config: Config, map_extent: sizing.MapExtent | tuple | float | None = None,
                 *, start_pose: np.ndarray | None = None, seed: int | None = None,
                 local_size: int | None = None, observed_cells: int = 0,
                 sensor: str | None = None, filter_config: rbpf.FilterConfig | None = None):
        _check_arguments(config, map_extent, seed, local_size, observed_cells, sensor,
                         filter_config)
        self.config = config
        self.start = np.zeros(3) if start_pose is None else _real(start_pose)
        if self.start is None or self.start.shape != (3,) or not np.isfinite(self.start).all():
            raise ConfigError(f"Online: start_pose must be 3 finite numbers (x, y, theta), "
                              f"got {start_pose!r:.80}")
        # the map's axes ([map] axes): the filter runs on them, as ``map_axes.on_map_axes``
        self.heading = map_axes_heading(config.map.axes, self.start)
        start_on_axes = turn_poses(self.start, -self.heading)
        self.localmap = localmap_params(config, sensor)
        if filter_config is None:
            L = self.localmap.size if local_size is None else int(local_size)
            if map_extent is None or isinstance(map_extent, (int, float)):
                size = DEFAULT_SIZE if map_extent is None else float(map_extent)
                extent = _extent(config, size, start_on_axes, L)
            else:
                extent = sizing.MapExtent(*map_extent)
            filter_config = sizing.extent_filter_config(config, extent, L, observed_cells, sensor)
        elif (map_extent is not None or local_size is not None or observed_cells
              or sensor is not None):
            raise ConfigError("Online: give either filter_config or map_extent, local_size, "
                              "observed_cells and sensor, not both")
        # a live run's window-store history starts at maps.LIVE_HISTORY and grows (_growth)
        cfg = maps.resolve_history(filter_config.validate(), maps.LIVE_HISTORY)
        available, what = sizing.map_memory()
        H, W = cfg.map_shape
        maps.check_memory(cfg, available, what, extent=f" (the live map, {H * cfg.resolution:.4g}"
                                                       f" x {W * cfg.resolution:.4g} m)")
        self._check_reach(cfg)
        self.cfg = cfg
        self._range_noise = (
            observations.RunningRangeNoise(config, cfg.local_size, cfg.resolution)
            if config.filter.range_noise == "profile" else None)
        self.params = sizing.filter_params(
            config, range_noise=None if self._range_noise is None else self._range_noise.profile)
        self.settings = observations.obs_settings(config)
        self.key = jax.random.key(config.filter.seed if seed is None else seed)
        self.state = rbpf.init(cfg, jnp.asarray(start_on_axes, jnp.float32))
        self._growth = maps.live_growth(cfg, config.map.pool_tiles, available, what)
        self._zero_obs = jnp.zeros((cfg.local_size, cfg.local_size, 2), jnp.float32)
        self._builder = LocalMapBuilder(self.localmap, axes_heading=self.heading)
        self._vo_pose = self.start.copy()
        self._poses: list[np.ndarray] = []      # per frame [J, 3]
        self._ancestors: list[np.ndarray] = []  # per frame [J]
        self._log_w: list[np.ndarray] = []      # per frame [J], after the frame
        self._resampled: list[bool] = []
        self._mean_on_axes: list[np.ndarray] = []  # per frame [3], the map lattice's axes
        self._footprints: list[np.ndarray] = []    # per frame [3] (local_map_footprint)
        self._times: list[float] = []
        self._latency: list[float] = []
        self._updated: list[bool] = []
        self.best: list[np.ndarray] = []        # per frame best pose [3]
        self.mean: list[np.ndarray] = []        # per frame mean pose [3]

    def _check_reach(self, cfg: rbpf.FilterConfig) -> None:
        lo = np.asarray(cfg.map_origin, np.float64)
        hi = lo + np.asarray(cfg.map_shape, np.float64) * cfg.resolution
        reach, limit = float(max(np.abs(lo).max(), np.abs(hi).max())), \
            coordinate_limit(cfg.resolution)
        if reach >= limit:
            raise ConfigError(f"Online: the map reaches {reach:.4g} m from the origin, where "
                              f"float32 no longer resolves {cfg.resolution:g} m cells (at most "
                              f"{limit:g} m); start nearer the origin or give a smaller extent")

    @property
    def frames(self) -> int:
        return len(self._times)

    @property
    def range_noise(self) -> np.ndarray | None:
        """[L * L] the running ``[filter] range_noise = "profile"`` estimate the weights use
        now (``observations.RunningRangeNoise``); None with "none"."""
        return None if self._range_noise is None else self._range_noise.profile

    def _observation(self, local_map) -> jax.Array:
        """Raw observation [L, L, 2] of local-map statistics [L, L, 3], as ``run_slam``'s,
        after the checks a Run file's local maps get (``run.checks.check_statistics``)."""
        L, t = self.cfg.local_size, self.frames
        stats = _real(local_map)
        if stats is None:
            raise ArgumentError(f"frame {t}: local_map must be [{L}, {L}, 3] statistics (n, sum "
                                f"z, sum z^2) as real numbers, got {local_map!r:.80}")
        if stats.shape != (L, L, 3):
            raise InputError(f"frame {t}: local_map must be [{L}, {L}, 3] statistics "
                             f"(n, sum z, sum z^2), got shape {list(stats.shape)}")

        def fail(message: str) -> None:
            raise InputError(f"frame {t}: local_map: {message}")

        def cell(bad: np.ndarray) -> str:
            i, j = (int(v) for v in np.argwhere(bad[0])[0])
            return f"cell ({i}, {j}) ({int(np.sum(bad))} cells in all)"

        stored = np.asarray(local_map).dtype
        check_statistics(stats[None], stored if stored.kind == "f" else np.float64, fail, cell)
        with np.errstate(over="ignore", invalid="ignore"):
            raw = cells.obs_from_stats(stats, 0.0).astype(np.float32)
        if not np.isfinite(raw).all():
            i, j = (int(v) for v in np.argwhere(~np.isfinite(raw).all(-1))[0])
            raise InputError(f"frame {self.frames}: local_map cell ({i}, {j}) statistics "
                             f"{stats[i, j].tolist()} are not finite in float32")
        return jnp.asarray(raw)

    def _control(self, control) -> np.ndarray:
        """The control [3] as float64, else an InputError naming the frame."""
        u = _real(control)
        if u is None or u.shape != (3,) or not np.isfinite(u).all():
            shown = u.tolist() if u is not None else control
            raise ArgumentError(f"frame {self.frames}: control must be 3 finite numbers (dx, "
                                f"dy, dtheta), got {shown!r:.80}")
        return u

    def push(self, control: np.ndarray, local_map: np.ndarray | None = None,
             time_s: float | None = None, lattice_heading: float = 0.0,
             vo_failed: bool = False) -> OnlineFrame:
        """One frame: ``control`` [3] the VO increment (dx, dy, dtheta) in the robot frame of
        the previous frame (``Run.controls``), ``local_map`` [L, L, 3] the statistics
        (n, sum z, sum z^2) of the local map completed at this frame or None, on a lattice
        turned by ``lattice_heading`` radians against the robot (``Run.lattice_headings``),
        ``time_s`` its time in seconds (for ``stats``; None: the frame index), ``vo_failed``
        whether the control came from the fallback odometry (``Run.vo_failed``: its motion
        noise is ``[motion] fallback_scale`` times the VO's). InputError for a
        malformed frame, ``chunk_checks.WeightError`` for non-finite weights, MapEdgeError
        past the map's edge."""
        t = self.frames
        u = self._control(control)
        stamp = float(t) if time_s is None else number_argument(time_s, f"frame {t}: time_s")
        lattice_heading = number_argument(lattice_heading, f"frame {t}: lattice_heading")
        if not isinstance(vo_failed, (bool, np.bool_)):
            raise ArgumentError(f"frame {t}: vo_failed must be True or False, got "
                                f"{vo_failed!r:.40}")
        if self._times and not stamp > self._times[-1]:
            raise InputError(f"frame {t}: time {stamp} s is not after the previous frame's "
                             f"{self._times[-1]} s")
        raw = self._zero_obs if local_map is None else self._observation(local_map)
        if self._growth is not None:
            self._growth.before(self.state.maps)
        t0 = time.perf_counter()
        if local_map is not None and self._range_noise is not None \
                and self._range_noise.add(local_map):  # same shape: no recompilation
            self.params = self.params._replace(range_noise=jnp.asarray(self._range_noise.profile))
        self.state, (info, best, mean) = online_step(
            self.state, self.key, jnp.int32(t), jnp.asarray(u, jnp.float32), raw,
            jnp.bool_(local_map is not None), jnp.float32(lattice_heading),
            jnp.bool_(vo_failed),
            self.settings, self.params, self.cfg)
        info, best, mean = jax.device_get((info, best, mean))
        self._mean_on_axes.append(np.asarray(mean, np.float64))
        best, mean = turn_poses(best, self.heading), turn_poses(mean, self.heading)
        seconds = time.perf_counter() - t0
        self._times.append(stamp)
        self._latency.append(seconds)
        self._updated.append(local_map is not None)
        self._poses.append(info.pose)
        self._ancestors.append(info.ancestors)
        self._log_w.append(info.log_w)
        self._resampled.append(bool(info.resampled))
        self._footprints.append(np.array([0.0, 0.0, -1.0]) if local_map is None else
                                observations.local_map_footprint(
                                    local_map, self.cfg.resolution, lattice_heading))
        self.best.append(best)
        self.mean.append(mean)
        self._vo_pose = integrate_controls(u[None], self._vo_pose)[0]
        batch = jax.tree.map(lambda x: np.asarray(x)[None], info)  # a one-frame chunk
        maps_so_far = int(sum(self._updated))
        chunk_checks.check_weights(batch, t, 1,
                                   {t: maps_so_far - 1 if local_map is not None else -1})
        chunk_checks.check_map_status(batch, t, self.cfg, automatic=self._growth is not None)
        if int(info.dropped_cells):
            raise InputError(f"frame {t}: the local map has more informative cells than "
                             f"observed_cells = {self.cfg.max_observed}; raise it (0: no cap)")
        if int(info.extent_violations):
            lo = np.asarray(self.cfg.map_origin)
            hi = lo + np.asarray(self.cfg.map_shape) * self.cfg.resolution
            raise MapEdgeError(
                f"frame {t}: the local map reached past the edge of the live map "
                f"(x {lo[0]:.2f} .. {hi[0]:.2f} m, y {lo[1]:.2f} .. {hi[1]:.2f} m) for "
                f"{int(info.extent_violations)} particles, whose cells beyond it were skipped; "
                "the map does not grow: give Online a larger map_extent")
        if self._growth is not None:  # an automatic pool or history running low grows
            # (the filter step recompiles)
            grown, self.cfg = self._growth.after(self.state.maps, self.cfg, batch.map_free, t + 1)
            self.state = self.state._replace(maps=grown)
        return OnlineFrame(pose=best, mean=mean, ess=float(info.ess), updated=bool(info.updated),
                           resampled=bool(info.resampled), seconds=seconds)

    def push_points(self, control: np.ndarray, points: np.ndarray,
                    time_s: float | None = None, vo_failed: bool = False) -> OnlineFrame:
        """One frame of robot-frame points [N, 3] (x forward, y left, z up): fused into local
        maps at the VO poses every [localmap] travel metres (``LocalMapBuilder``, the first at
        the first frame, as ``build_local_maps`` does), then ``push``."""
        u = self._control(control)
        points = array_argument(points, f"frame {self.frames}: points", (None, 3),
                                "robot-frame points (x forward, y left, z up)")
        pose = integrate_controls(u[None], self._vo_pose)[0]
        stats = self._builder.add(pose, points)
        if self.frames == 0 and stats is None:
            stats = self._builder.flush()
        heading = self._builder.lattice_headings[-1] if stats is not None else 0.0
        return self.push(control, stats, time_s, heading, vo_failed)

    def particles(self) -> Particles:
        """The particles now: poses [J, 3], normalised weights [J] and, with ``[motion]
        noise_spread`` > 1, each one's factor on the motion stds [J]."""
        pose, log_w, noise = jax.device_get((self.state.pose, self.state.log_w,
                                             self.state.noise_scale))
        return Particles(turn_poses(np.asarray(pose, np.float64), self.heading),
                         np.exp(np.asarray(log_w, np.float64)),
                         None if noise is None else np.asarray(noise, np.float64))

    def map(self) -> GridMap:
        """The map the batch run would report after this frame (k, S float64 on the live
        extent): the particle's of ``rbpf.map_particle`` for ``[filter] estimate``."""
        slot = rbpf.map_particle(self.config.filter.estimate, self.state.pose, self.state.log_w,
                                 self.state.best)
        k, S = rbpf.particle_map(self.state, slot, self.cfg)
        return GridMap(np.asarray(k, np.float64), np.asarray(S, np.float64),
                       tuple(self.cfg.map_origin), float(self.cfg.resolution), self.heading)

    def path(self, estimate: str | None = None) -> np.ndarray:
        """[T, 3] the trajectory so far as the batch run would report it after this frame:
        ``estimate`` one of ``choices.ESTIMATES`` (None: the config's ``[filter] estimate``),
        "best" the best particle's path through its ancestry (``SlamResult.best_path``), "mean"
        each frame's weighted mean (``Online.mean``), "smoothed" and "steps" the particle
        smoother's mean path and mean-step path over the ancestry with the weights now, "mode"
        and "mode_mean" the densest particle's path and the smoother's mean over its 1 m
        neighbourhood, "local_steps" the mean steps each weighed by the factors that bear on
        it so far."""
        estimate = self.config.filter.estimate if estimate is None else estimate
        if estimate not in choices.ESTIMATES:
            raise ConfigError(f"Online.path: estimate must be one of "
                              f"{', '.join(choices.ESTIMATES)}, got {estimate!r}")
        if not self._poses:
            return np.zeros((0, 3))
        if estimate == "mean":
            return np.stack(self.mean)
        history = rbpf.step_history(np.stack(self._log_w), np.asarray(self._resampled),
                                    np.stack(self._mean_on_axes), np.stack(self._footprints))
        path = rbpf.ancestry_path(estimate, jnp.asarray(np.stack(self._poses)),
                                  jnp.asarray(np.stack(self._ancestors)), self.state.log_w,
                                  self.state.best, history)
        return turn_poses(np.asarray(path, np.float64), self.heading)

    def stats(self) -> OnlineStats:
        """Timing so far (``OnlineStats``)."""
        lat = np.asarray(self._latency[1:], np.float64)
        upd = lat[np.asarray(self._updated[1:], bool)]
        log = self._times[-1] - self._times[0] if self._times else 0.0
        seconds = float(lat.sum())
        rtf = log / seconds if seconds > 0 else float("nan")
        return OnlineStats(frames=self.frames, updates=int(sum(self._updated)),
                           compile_seconds=self._latency[0] if self._latency else 0.0,
                           seconds=seconds, log_seconds=log, realtime_factor=rtf,
                           frame_latency=lat, update_latency=upd)
