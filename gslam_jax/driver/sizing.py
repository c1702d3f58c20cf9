"""The filter's static settings for a Run: the map extent sized from the VO path (and a prior
map), the automatic choices (map store, particle block, ESS target), the memory and float32
checks that come before any allocation, the motion and weighting parameters, and each frame's
motion-noise scale."""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gslam_jax import choices, rbpf
from gslam_jax.config import Config, ConfigError
from gslam_jax.driver.machine import device_memory_limit, physical_memory, process_memory_limit
from gslam_jax.driver.map_reuse import PriorMap, check_prior, known_box
from gslam_jax.driver.observations import run_range_noise
from gslam_jax.gridmap import place
from gslam_jax.rbpf import maps
from gslam_jax.rbpf.motion import MotionParams
from gslam_jax.run import Run, RunError
from gslam_jax.run.checks import coordinate_limit, float32_spacing

__all__ = ["MapExtent", "map_extent", "check_float32_reach", "observed_cells", "map_memory",
           "filter_config", "extent_filter_config", "resolve_ess_target",
           "resolve_proposal_draws", "motion_params", "filter_params", "fallback_frames"]


class MapExtent(NamedTuple):
    origin: tuple[float, float]
    shape: tuple[int, int]


def map_extent(vo_poses: np.ndarray, local_size: int, resolution: float, margin: float,
               window: int, lattice: tuple[float, float] | None = None,
               cover: tuple[np.ndarray, np.ndarray] | None = None) -> MapExtent:
    """Dense map extent from the VO path: its bounding box, plus the reach of a rotated local
    map, plus ``margin`` metres for drift; sides are multiples of 8 and at least one window.
    With ``lattice`` (a prior map's origin) the extent's origin is a whole number of cells
    from it, and the box ``cover`` = (lo [2], hi [2]) (the prior's known cells) is covered too.
    A ConfigError names [map] margin when the extent is not even a finite number of metres."""
    xy = np.asarray(vo_poses, dtype=np.float64)[:, :2]
    reach = 0.5 * window * resolution + margin
    with np.errstate(over="ignore", invalid="ignore"):  # an infinite extent: reported below
        lo = xy.min(axis=0) - reach
        hi = xy.max(axis=0) + reach
        if cover is not None:
            lo, hi = np.minimum(lo, cover[0]), np.maximum(hi, cover[1])
        if lattice is not None:
            base = np.asarray(lattice, np.float64)
            lo = base + np.floor((lo - base) / resolution) * resolution
        cells_needed = (hi - lo) / resolution
    if not np.isfinite(cells_needed).all():
        raise ConfigError(f"the map extent is not finite: [map] margin {margin:g} m around a VO "
                          f"path spanning {np.ptp(xy, axis=0).tolist()} m at [map] resolution "
                          f"{resolution:g} m; use a smaller [map] margin")
    # Python ints: a huge extent stays huge (and fails the memory check) instead of wrapping.
    shape = tuple(max(window, 8 * math.ceil(math.ceil(float(n)) / 8)) for n in cells_needed)
    return MapExtent((float(lo[0]), float(lo[1])), shape)  # type: ignore[arg-type]


def check_float32_reach(vo_poses: np.ndarray, extent: MapExtent, resolution: float,
                        margin: float) -> None:
    """RunError naming the frame where the VO path, or ConfigError naming [map] margin where the
    map ``extent`` around it, reaches ``run.checks.coordinate_limit(resolution)`` metres from the
    origin: there the filter's float32 poses no longer resolve the map's cells."""
    limit = coordinate_limit(resolution)
    xy = np.asarray(vo_poses, np.float64)[:, :2]
    far = np.abs(xy).max(axis=1)
    if far.max() >= limit:
        t = int(np.argmax(far >= limit))
        raise RunError(f"field 'controls': the VO path reaches ({xy[t, 0]:.6g}, {xy[t, 1]:.6g}) m "
                       f"at frame {t}, {far[t]:.4g} m from the origin; float32 poses there are "
                       f"{float32_spacing(far[t]):.3g} m apart, too coarse for "
                       f"[map] resolution {resolution:g} m (at most {limit:g} m from the origin)")
    lo = np.asarray(extent.origin, np.float64)
    hi = lo + np.asarray(extent.shape, np.float64) * resolution
    reach = float(max(np.abs(lo).max(), np.abs(hi).max()))
    if reach >= limit:
        raise ConfigError(f"[map] margin {margin:g} m around the VO path takes the map to "
                          f"{reach:.4g} m from the origin, where float32 no longer resolves "
                          f"[map] resolution {resolution:g} m (at most {limit:g} m from the "
                          "origin); use a smaller [map] margin")


def observed_cells(run: Run, multiple: int = 128) -> int:
    """The filter's static cap M on observed cells per update: the most informative cells
    (n >= 2 points) of any of the Run's local maps, rounded up to ``multiple``, at most L*L.
    Every update then evaluates M cells instead of L*L (about 40% of them at 10 m range)."""
    if run.num_local_maps == 0:
        return 0
    L = int(run.local_maps.shape[1])
    most = int(np.max(np.sum(run.local_maps[..., 0] >= 2, axis=(1, 2))))
    return min(L * L, multiple * max(1, math.ceil(most / multiple)))


def map_memory() -> tuple[int, str]:
    """(bytes, what): the memory the maps live in: the accelerator's limit where the device
    reports one, else the machine's physical memory or the process's limit (``ulimit -v``)
    when that is lower."""
    limit = device_memory_limit()
    if limit:
        return int(limit), f"{jax.devices()[0].device_kind} memory"
    physical, process = physical_memory(), process_memory_limit()
    if process is not None and process < physical:
        return process, "memory this process may use (ulimit -v)"
    return physical, "physical memory"


def filter_config(config: Config, run: Run, prior: PriorMap | None = None
                  ) -> rbpf.FilterConfig:
    """Static filter settings for this Run: the map sized from its VO path, ``store = "auto"``
    resolved for this machine's memory (``maps.choose_store``) and ``particle_block = 0``
    for the default backend (``FilterConfig.update_block``); a ConfigError when the particle
    maps would not fit in memory (``maps.check_memory``).

    With a ``prior`` map, ``run`` must start at ``prior.start`` (``rebase``): the map then lies
    on the prior's lattice and covers its known cells as well as the VO path, whose reach grows
    by three standard deviations of the start position."""
    if not math.isclose(run.resolution, config.map.resolution, rel_tol=1e-6):
        raise ConfigError(f"run resolution {run.resolution} m differs from [map] resolution "
                         f"{config.map.resolution} m; rebuild the local maps or change the config")
    L = int(run.local_maps.shape[1]) if run.num_local_maps else 8
    probe = rbpf.FilterConfig.from_config(config, map_shape=(8, 8), map_origin=(0.0, 0.0),
                                          local_size=L)
    margin, lattice, cover = config.map.margin, None, None
    if prior is not None:
        check_prior(prior, config)
        margin += 3.0 * float(np.hypot(*np.asarray(prior.start_sigma, float)[:2]))
        lattice, cover = prior.grid.origin, known_box(prior.grid)
    extent = map_extent(run.vo_poses(), L, config.map.resolution, margin, probe.window,
                        lattice, cover)
    cfg = extent_filter_config(config, extent, L, observed_cells(run), run.sensor)
    available, what = map_memory()
    if prior is not None and cfg.store == "shared" and not cfg.pool_tiles:
        cfg = _prior_pool(cfg, prior)
    cfg = maps.resolve_history(cfg, int(np.sum(np.asarray(run.obs_index) >= 0)),
                               run.local_maps)
    try:
        maps.check_memory(cfg, available, what, extent=_extent_cause(run, config))
    except ConfigError as err:
        _check_steps(run, str(err))
        raise
    check_float32_reach(run.vo_poses(), extent, config.map.resolution, config.map.margin)
    return cfg


def extent_filter_config(config: Config, extent: MapExtent, local_size: int,
                         observed: int = 0, sensor: str | None = None) -> rbpf.FilterConfig:
    """Static filter settings on a given map ``extent`` with local maps of side ``local_size``
    and at most ``observed`` informative cells each (0: L*L): the config's [filter] and [map]
    settings, ``store = "auto"`` resolved for this machine's memory (``maps.choose_store``),
    ``particle_block = 0`` for the default backend, and ``ess_target = 0`` and
    ``proposal_draws = "auto"`` for the local maps' ``sensor`` (``resolve_ess_target``,
    ``resolve_proposal_draws``). The memory check is the caller's."""
    f = config.filter
    cfg = rbpf.FilterConfig.from_config(
        config, map_shape=tuple(extent.shape), map_origin=tuple(extent.origin),
        local_size=local_size, observed_cells=observed,
        ess_target=resolve_ess_target(f.ess_target, sensor),
        proposal_draws=resolve_proposal_draws(f.proposal_draws, sensor))
    available, what = map_memory()
    cfg = maps.choose_store(cfg, available, what).validate()
    return cfg._replace(particle_block=cfg.update_block)


def _sensor(sensor: str | None) -> str:
    """The local maps' sensor (None: "points"). ConfigError naming an unknown one."""
    if sensor is not None and sensor not in choices.SENSORS:
        raise ConfigError(f"sensor must be one of {', '.join(choices.SENSORS)}, got {sensor!r}")
    return "points" if sensor is None else sensor


def resolve_ess_target(ess_target: float, sensor: str | None) -> float:
    """``[filter] ess_target``, or for 0 (automatic) ``choices.AUTO_ESS_TARGET`` of the local
    maps' ``sensor`` (None: "points"). ConfigError naming an unknown sensor."""
    return ess_target or choices.AUTO_ESS_TARGET[_sensor(sensor)]


def resolve_proposal_draws(draws: str, sensor: str | None) -> str:
    """``[filter] proposal_draws``, or for "auto" ``choices.AUTO_PROPOSAL_DRAWS`` of the local
    maps' ``sensor`` (None: "points"). ConfigError naming an unknown sensor."""
    return choices.AUTO_PROPOSAL_DRAWS[_sensor(sensor)] if draws == "auto" else draws


def _prior_pool(cfg: rbpf.FilterConfig, prior: PriorMap) -> rbpf.FilterConfig:
    """``cfg`` with the automatic pool of the shared store (``maps.pool_tiles``) enlarged by
    the prior's tiles, which stay in the pool besides the run's own history; never more than
    every particle's whole map."""
    grid = place(prior.grid, cfg.map_origin, cfg.map_shape)
    pool = maps.pool_tiles(cfg) + maps.prior_tiles(grid.k, cfg)
    return cfg._replace(pool_tiles=min(pool, maps.whole_maps_tiles(cfg)))


def _extent_cause(run: Run, config: Config) -> str:
    """What sizes the map, for the memory message: the VO path's span and the margin."""
    span = np.ptp(run.vo_poses()[:, :2], axis=0)
    return (f" (the map covers the VO path, {span[0]:.4g} x {span[1]:.4g} m, plus [map] margin "
            f"{config.map.margin:g} m on each side)")


def _check_steps(run: Run, memory: str) -> None:
    """RunError naming the frame when one control alone spans most of a map too large for
    memory (a corrupt or mis-scaled control, not a large area): ``memory`` is the message."""
    xy = run.vo_poses()[:, :2]
    steps = np.hypot(run.controls[:, 0], run.controls[:, 1])
    t = int(np.argmax(steps))
    median = float(np.median(steps))
    if steps[t] > 0.5 * float(np.ptp(xy, axis=0).max()) and steps[t] > 1000 * max(median, 1e-3):
        raise RunError(f"field 'controls': frame {t} moves {steps[t]:.4g} m in one step (the "
                       f"median step is {median:.3g} m), which makes the map too large: "
                       f"{memory.split(';')[0]}; check the Run's controls (units?)")


def motion_params(config: Config) -> MotionParams:
    """``[motion]`` as the filter's ``MotionParams`` (float32 scalars)."""
    m = config.motion
    return MotionParams(jnp.float32(m.alpha_d), jnp.float32(m.alpha_theta_d),
                        jnp.float32(m.alpha_theta), jnp.float32(m.alpha_cross),
                        jnp.float32(m.fallback_scale))


def filter_params(config: Config, run: Run | None = None,
                  range_noise: np.ndarray | None = None) -> rbpf.FilterParams:
    """The filter's continuous parameters: ``[motion]``, ``[filter]`` beta_prev / beta_new,
    and with ``[filter] range_noise = "profile"`` the measurement variance per local cell:
    ``range_noise`` [L * L] when given (``online.Online``'s running estimate), else estimated
    from ``run`` (``observations.run_range_noise``; ConfigError with neither)."""
    noise = None
    if config.filter.range_noise == "profile":
        if range_noise is not None:
            noise = jnp.asarray(range_noise, jnp.float32)
        elif run is None:
            raise ConfigError("[filter] range_noise = \"profile\" is estimated from the run's "
                              "local maps, and neither the run nor a profile was given")
        else:
            noise = jnp.asarray(run_range_noise(run, config))
    return rbpf.FilterParams(
        motion=motion_params(config),
        beta_prev=jnp.float32(config.filter.beta_prev),
        beta_new=jnp.float32(config.filter.beta_new), range_noise=noise)


def fallback_frames(run: Run, config: Config, keep: bool = False) -> np.ndarray | None:
    """[T] bool: the frames whose control came from the fallback odometry (``Run.vo_failed``),
    whose motion noise the filter scales by ``[motion] fallback_scale`` (``rbpf.step``).
    None when no frame did, or when the scale is 1 and ``keep`` is false: the filter then
    runs without the scaling in its program, as before the setting. ``keep``: the flags
    even at a scale of 1, for a search or a tuning of ``fallback_scale``."""
    if run.vo_failed is None or not np.any(run.vo_failed):
        return None
    if config.motion.fallback_scale == 1.0 and not keep:
        return None
    return np.asarray(run.vo_failed, bool).copy()
