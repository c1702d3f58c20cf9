"""Running Gamma-SLAM on a Run: sizing the map, converting observations, chunked scan, results.

This is the host-side driver the CLI, the experiments and the benchmarks share. The filter math
lives in ``rbpf``; this module only prepares its inputs and collects its outputs.
"""

from __future__ import annotations

import math
import time
import warnings
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gslam_jax import choices, rbpf
from gslam_jax.rbpf import cells, maps, tilestore
from gslam_jax.config import Config, ConfigError
from gslam_jax.errors import InputError
from gslam_jax.gridmap import GridMap, place
from gslam_jax.machine import device_memory_limit, physical_memory, process_memory_limit
from gslam_jax.rbpf.motion import MotionParams
from gslam_jax.run import (Run, RunError, check_start_pose, coordinate_limit, describe_cells,
                           float32_spacing, known_positions)

__all__ = ["MapExtent", "map_extent", "check_float32_reach", "observed_cells", "filter_config",
           "extent_filter_config", "resolve_ess_target",
           "filter_params", "local_observations", "raw_observations", "ObsSettings",
           "obs_settings", "refine_observations", "map_observations", "map_memory", "RunArrays",
           "run_arrays", "ground_truth_mask",
           "require_ground_truth", "SlamResult", "run_slam", "ExtentWarning", "WeightError",
           "PriorMap", "check_prior", "rebase", "prior_summary", "START_STREAM", "ChunkReport"]

START_STREAM = 0x57A7  # folded into the filter's key for the start poses drawn around a prior


class ExtentWarning(UserWarning):
    """Particles observed cells outside the map extent (those cells were skipped)."""


class WeightError(InputError):
    """The filter cannot weigh the data: an update left non-finite particle weights (ESS or
    log-likelihood not finite); names the frame and the local map."""


class MapExtent(NamedTuple):
    origin: tuple[float, float]
    shape: tuple[int, int]


class PriorMap(NamedTuple):
    """Map reuse: a finished map (run A's) the particles start with, localise in and extend.

    ``start`` is the run's start pose in the map's frame; the particles start there, spread by
    N(0, diag(start_sigma^2)) (x, y in metres, heading in radians; zeros: every particle at
    ``start``). ``source`` says where the map was read from (for the results)."""

    grid: GridMap
    start: np.ndarray | None  # [3] x, y, theta; None: to be located (``relocalise``)
    start_sigma: np.ndarray   # [3] standard deviations, >= 0
    source: str = ""
    located: dict | None = None  # how the start was located, when it was (summary.json)


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
    map ``extent`` around it, reaches ``run.coordinate_limit(resolution)`` metres from the
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


def check_prior(prior: PriorMap, config: Config) -> None:
    """ConfigError when the prior map cannot be the filter's map: another resolution than
    [map] resolution (the filter's grid lies on the prior's lattice), or a start pose or
    spread that is not finite (the spread must be >= 0), or a start beyond float32's reach of
    the map's cells (``run.check_start_pose``)."""
    res = prior.grid.resolution
    if not math.isclose(res, config.map.resolution, rel_tol=1e-6):
        raise ConfigError(f"the prior map {prior.source or ''} has resolution {res:g} m, "
                          f"[map] resolution is {config.map.resolution:g} m: they must be "
                          "equal (set [map] resolution to the prior map's)")
    if prior.start is None:  # located later, from the run (``locate_prior_start``)
        return
    start, sigma = np.asarray(prior.start, float), np.asarray(prior.start_sigma, float)
    if start.shape != (3,) or not np.isfinite(start).all():
        raise ConfigError(f"the start pose in the prior map must be 3 finite numbers "
                          f"(x, y, theta), got {start.tolist()}")
    if sigma.shape != (3,) or not (np.isfinite(sigma).all() and (sigma >= 0).all()):
        raise ConfigError(f"the start pose's standard deviations must be 3 finite numbers "
                          f">= 0 (x, y, theta), got {sigma.tolist()}")

    def fail(field: str, msg: str) -> None:
        raise ConfigError(f"--start (the start pose in the prior map): {msg}")

    check_start_pose(start, res, fail)  # within float32's reach of the map's cells


def locate_prior_start(prior: PriorMap, run: Run, config: Config) -> PriorMap:
    """``prior`` with its start located from ``run`` when it has none
    (``relocalise.locate_start``: the run's first metres aligned in the prior map); the
    spread is the given one when it is not zero, else the located one. AlignmentRefused (an
    InputError) when the run's start cannot be told from the map."""
    if prior.start is not None:
        return prior
    from gslam_jax.relocalise import locate_start

    found = locate_start(prior.grid, run)
    given = np.asarray(prior.start_sigma, float)
    sigma = given if np.any(given > 0) else found.sigma
    located = {"frames": found.frames, **found.alignment.summary()}
    prior = prior._replace(start=found.start, start_sigma=sigma, located=located)
    check_prior(prior, config)
    return prior


def rebase(run: Run, start: np.ndarray) -> Run:
    """``run`` starting at ``start`` (a pose in another frame, e.g. a prior map's): its VO path
    (``Run.vo_poses``) and everything the filter does are then in that frame."""
    return run._replace(initial_pose=np.asarray(start, np.float64).copy())


def _prior_cover(grid: GridMap) -> tuple[np.ndarray, np.ndarray] | None:
    """(lo, hi) corners of the box around the prior's known cells; None when it has none."""
    i, j = np.nonzero(grid.known)
    if not i.size:
        return None
    r, o = grid.resolution, np.asarray(grid.origin, np.float64)
    return (o + r * np.array([i.min(), j.min()]), o + r * np.array([i.max() + 1, j.max() + 1]))


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
    f = config.filter
    probe = rbpf.FilterConfig(num_particles=f.particles, map_shape=(8, 8), map_origin=(0.0, 0.0),
                              resolution=config.map.resolution, local_size=L,
                              unknown_cells=f.unknown_cells)
    margin, lattice, cover = config.map.margin, None, None
    if prior is not None:
        check_prior(prior, config)
        margin += 3.0 * float(np.hypot(*np.asarray(prior.start_sigma, float)[:2]))
        lattice, cover = prior.grid.origin, _prior_cover(prior.grid)
    extent = map_extent(run.vo_poses(), L, config.map.resolution, margin, probe.window,
                        lattice, cover)
    cfg = extent_filter_config(config, extent, L, observed_cells(run), run.sensor)
    available, what = map_memory()
    if prior is not None and cfg.store == "shared" and not cfg.pool_tiles:
        cfg = _prior_pool(cfg, prior)
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
    ``particle_block = 0`` for the default backend and ``ess_target = 0`` for the local maps'
    ``sensor`` (``resolve_ess_target``). The memory check is the caller's."""
    f = config.filter
    cfg = rbpf.FilterConfig(
        num_particles=f.particles, map_shape=tuple(extent.shape), map_origin=tuple(extent.origin),
        resolution=config.map.resolution, local_size=local_size, resampler=f.resampler,
        resample_ratio=f.resample_ratio, unknown_cells=f.unknown_cells,
        unknown_samples=f.unknown_samples, observed_cells=observed,
        particle_block=f.particle_block, tempering=f.tempering,
        ess_target=resolve_ess_target(f.ess_target, sensor),
        store=config.map.store, tile=config.map.tile, pool_tiles=config.map.pool_tiles,
        proposal=f.proposal, proposal_points=f.proposal_points, proposal_span=f.proposal_span,
        proposal_stages=f.proposal_stages)
    available, what = map_memory()
    cfg = maps.choose_store(cfg, available, what).validate()
    return cfg._replace(particle_block=cfg.update_block)


def resolve_ess_target(ess_target: float, sensor: str | None) -> float:
    """``[filter] ess_target``, or for 0 (automatic) ``choices.AUTO_ESS_TARGET`` of the local
    maps' ``sensor`` (None: "points"). ConfigError naming an unknown sensor."""
    if sensor is not None and sensor not in choices.SENSORS:
        raise ConfigError(f"sensor must be one of {', '.join(choices.SENSORS)}, got {sensor!r}")
    return ess_target or choices.AUTO_ESS_TARGET["points" if sensor is None else sensor]


def _prior_pool(cfg: rbpf.FilterConfig, prior: PriorMap) -> rbpf.FilterConfig:
    """``cfg`` with the automatic pool of the shared store (``maps.pool_tiles``) enlarged by
    the prior's tiles, which stay in the pool besides the run's own history; never more than
    every particle's whole map."""
    grid = place(prior.grid, cfg.map_origin, cfg.map_shape)
    ty, tx = tilestore.pages_per_side(cfg.map_shape, cfg.tile)
    pool = maps.pool_tiles(cfg) + tilestore.prior_tiles(grid.k, cfg.tile)
    return cfg._replace(pool_tiles=min(pool, cfg.num_particles * ty * tx))


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


def filter_params(config: Config) -> rbpf.FilterParams:
    m = config.motion
    return rbpf.FilterParams(
        motion=MotionParams(jnp.float32(m.alpha_d), jnp.float32(m.alpha_theta_d),
                            jnp.float32(m.alpha_theta)),
        beta_prev=jnp.float32(config.filter.beta_prev),
        beta_new=jnp.float32(config.filter.beta_new))


def local_observations(run: Run, min_variance: float, weight: float = 1.0,
                       min_points: int = 2) -> np.ndarray:
    """[max(M, 1), L, L, 2] float32 observations (k, S) (``cells.obs_from_stats`` with the
    ``[map]`` settings min_variance, obs_weight and min_points); float64 on the host, then cast.

    A RunError, naming the local map and a frame that uses it, when a value is not finite in
    float32 (statistics finite in float64 may overflow float32's range, about 3.4e38)."""
    if run.num_local_maps == 0:
        return np.zeros((1, 8, 8, 2), np.float32)
    with np.errstate(over="ignore", invalid="ignore"):
        obs = cells.obs_from_stats(run.local_maps, min_variance, weight,
                                   min_points).astype(np.float32)
    bad = ~np.isfinite(obs).all(axis=-1)
    if bad.any():
        m, i, j = (int(v) for v in np.argwhere(bad)[0])
        raise RunError(
            f"field 'local_maps': {describe_cells(bad, run.obs_index)}: the statistics "
            f"{run.local_maps[m, i, j].tolist()} (n, sum z, sum z^2) give an observation "
            f"(k, S) = {obs[m, i, j].tolist()} beyond float32, which the filter computes in; "
            f"check that local map's statistics")
    return obs


def raw_observations(run: Run) -> np.ndarray:
    """The Run's raw observations: ``local_observations`` with no floor, weight 1 and the
    two-point threshold, which ``refine_observations`` turns into the filter's on the device."""
    return local_observations(run, 0.0)


class ObsSettings(NamedTuple):
    """The ``[map]`` observation settings, float32 scalars on the device (traced: the search
    and the tuner vary them without a recompilation)."""

    min_variance: jax.Array
    obs_weight: jax.Array
    min_points: jax.Array


def obs_settings(config: Config) -> ObsSettings:
    """The config's ``[map]`` min_variance, obs_weight and min_points."""
    m = config.map
    return ObsSettings(jnp.float32(m.min_variance), jnp.float32(m.obs_weight),
                       jnp.float32(m.min_points))


def refine_observations(raw: jax.Array, settings: ObsSettings) -> jax.Array:
    """The filter's observations [M, L, L, 2]: ``raw_observations`` floored, weighted and
    thresholded by ``settings`` on the device (``cells.refine_obs``). The one route of the
    observation settings, for a run as for a search or the tuner."""
    return cells.refine_obs(raw, settings.min_variance, settings.obs_weight,
                            settings.min_points)


def map_observations(run: Run, config: Config) -> jax.Array:
    """The filter's observations of ``run`` under the config's ``[map]`` settings:
    ``raw_observations`` refined on the device (``refine_observations``)."""
    return refine_observations(jnp.asarray(raw_observations(run)), obs_settings(config))


class RunArrays(NamedTuple):
    """A Run's device arrays, as the batched search and the tuner feed them to the filter."""

    controls: jax.Array    # [T, 3]
    obs_index: jax.Array   # [T]
    local_obs: jax.Array   # [M, L, L, 2] raw observations (``raw_observations``)
    reference: jax.Array   # [T, 3] ground truth (zeros where unknown)
    mask: jax.Array        # [T] frames with a ground-truth position (``ground_truth_mask``)
    start: jax.Array       # [3]
    obs: ObsSettings       # the config's settings for ``refine_observations``


def ground_truth_mask(run: Run) -> np.ndarray:
    """[T] bool: frames whose ground-truth position (x, y) is finite, as
    ``metrics.errors_over_known_frames`` scores them. The RMS objective of the search and the
    supervised loss of the tuner use positions only: a NaN heading drops no frame."""
    if run.ground_truth is None:
        return np.zeros(run.num_frames, bool)
    return known_positions(run.ground_truth)


def require_ground_truth(mask: jax.Array | np.ndarray, objective: str,
                         error: type[InputError]) -> None:
    """``error`` when ``mask`` (``RunArrays.mask``) marks no frame: an objective over no frame
    with ground truth would be 0 for every parameter value."""
    if not np.any(np.asarray(mask)):
        raise error(f"objective '{objective}' needs ground truth, but the run's ground_truth "
                    f"has no frame with a finite position (x, y); use objective 'loglik'")


def run_arrays(run: Run, config: Config) -> tuple[RunArrays, rbpf.FilterConfig]:
    """Device arrays of ``run`` (raw observations, to be refined on the device with the
    config's or searched settings) and the static filter config for it."""
    T = run.num_frames
    gt = run.ground_truth if run.ground_truth is not None else np.full((T, 3), np.nan)
    arrays = RunArrays(
        controls=jnp.asarray(run.controls, jnp.float32),
        obs_index=jnp.asarray(run.obs_index, jnp.int32),
        local_obs=jnp.asarray(raw_observations(run)),
        reference=jnp.asarray(np.nan_to_num(gt), jnp.float32),
        mask=jnp.asarray(ground_truth_mask(run)),
        start=jnp.asarray(run.start_pose(), jnp.float32),
        obs=obs_settings(config))
    return arrays, filter_config(config, run)


def _check_weights(info: rbpf.StepInfo, start: int, frames: int, obs_index: np.ndarray) -> None:
    """WeightError at the first of ``frames`` frames from ``start`` whose ESS or log_lik is
    not finite (NaN weights would otherwise be carried silently: no resampling, NaN poses)."""
    ess = np.asarray(info.ess)[:frames]
    log_lik = np.asarray(info.log_lik)[:frames]
    bad = ~(np.isfinite(ess) & np.isfinite(log_lik))
    if bad.any():
        i = int(np.argmax(bad))
        t = start + i
        m = int(obs_index[t])
        what = (f"the filter cannot weigh local map {m}: the update with it left non-finite "
                f"particle weights" if m >= 0 else
                "non-finite particle weights at a frame without a local map")
        check = (f"check local map {m}'s statistics (n, sum z, sum z^2 per cell)" if m >= 0
                 else "check the run's controls and the local maps before this frame")
        raise WeightError(
            f"frame {t}: {what} (ESS {float(ess[i])}, evidence (log-likelihood) "
            f"{float(log_lik[i])}, not finite); {check}")


def _check_map_status(info: rbpf.StepInfo, start: int, cfg: rbpf.FilterConfig) -> None:
    """The map store's error (``maps.check_status``) at the first frame it flagged."""
    status = np.asarray(info.map_status)
    if status.any():
        i = int(np.argmax(status != 0))
        maps.check_status(status[i], cfg, where=f"frame {start + i}: ")


class SlamResult(NamedTuple):
    """Host-side (NumPy) outputs of one Gamma-SLAM run."""

    best_path: np.ndarray      # [T, 3] the final best particle's path through its ancestry
    smoothed_path: np.ndarray  # [T, 3] final-weighted mean of every final particle's ancestry
    best_pose: np.ndarray      # [T, 3] highest-weight particle per frame
    mean_pose: np.ndarray      # [T, 3] weighted mean per frame
    vo_path: np.ndarray        # [T, 3] VO-only trajectory
    ess: np.ndarray            # [T]
    resampled: np.ndarray      # [T] bool
    updated: np.ndarray        # [T] bool
    log_lik: np.ndarray        # [T] log mean weight increments
    exponent: np.ndarray       # [T] tempering exponent of each update (1: the paper's beta)
    kmap: np.ndarray           # [H, W] best particle's map
    smap: np.ndarray           # [H, W]
    map_origin: tuple[float, float]
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

    @property
    def path(self) -> np.ndarray:
        """[T, 3] the reported trajectory ([filter] estimate): ``best_path``, ``mean_pose`` or
        ``smoothed_path``."""
        return {"best": self.best_path, "mean": self.mean_pose,
                "smoothed": self.smoothed_path}[self.estimate]

    @property
    def grid(self) -> GridMap:
        """The best particle's map as a ``GridMap`` (float64), e.g. for ``align_maps``."""
        return GridMap(np.asarray(self.kmap, np.float64), np.asarray(self.smap, np.float64),
                       tuple(self.map_origin), float(self.resolution))


class ChunkReport(NamedTuple):
    """What ``run_slam`` hands its ``on_chunk`` callback after each chunk of frames: host
    values, except ``state``, which is donated to the next chunk's scan (use it within the
    call, e.g. ``rbpf.particle_map(state, int(state.best), cfg)`` for the best map so far)."""

    run: Run                 # the run being filtered (rebased onto a prior map's start)
    start: int               # the chunk's first frame
    info: rbpf.StepInfo      # per frame of the chunk: particle poses [n, J, 3], ess [n], ...
    best_pose: np.ndarray    # [n, 3] highest-weight particle per frame
    mean_pose: np.ndarray    # [n, 3] weighted mean per frame
    state: rbpf.FilterState  # after the chunk's last frame
    cfg: rbpf.FilterConfig


def _prior_state(prior: PriorMap, cfg: rbpf.FilterConfig, key: jax.Array) -> rbpf.FilterState:
    """The filter's start with a prior map: the prior placed on the filter's grid in every
    particle's map, the particles at ``prior.start`` spread by ``prior.start_sigma`` (drawn
    from ``key`` folded with START_STREAM; a zero spread draws nothing)."""
    grid = place(prior.grid, cfg.map_origin, cfg.map_shape)
    if cfg.store == "shared":
        need, have = tilestore.prior_tiles(grid.k, cfg.tile), maps.pool_tiles(cfg)
        if need > have:
            raise ConfigError(f"the prior map needs {need} tiles of the shared map store, "
                              f"more than its [map] pool_tiles = {have}; raise [map] "
                              "pool_tiles (0: automatic)")
    sigma = np.asarray(prior.start_sigma, np.float64)
    return rbpf.init(cfg, jnp.asarray(prior.start, jnp.float32),
                     (jnp.asarray(grid.k, jnp.float32), jnp.asarray(grid.S, jnp.float32)),
                     jax.random.fold_in(key, START_STREAM),
                     jnp.asarray(sigma, jnp.float32) if sigma.any() else None)


def prior_summary(prior: PriorMap, result: SlamResult) -> dict:
    """What ``summary.json`` records of a run on a prior map: where the map came from, the
    start pose and its spread, the prior's known cells and the cells the run added to it."""
    grid = place(prior.grid, result.map_origin, result.kmap.shape)
    known = np.asarray(result.kmap) > 0
    return {"path": prior.source, "start": np.asarray(prior.start, float).tolist(),
            "start_sigma": np.asarray(prior.start_sigma, float).tolist(),
            **({"start_located": prior.located} if prior.located is not None else {}),
            "origin": list(prior.grid.origin), "resolution": prior.grid.resolution,
            "prior_known_cells": int(grid.known.sum()),
            "cells_added": int(np.sum(known & ~grid.known)),
            "known_cells": int(known.sum())}


def run_slam(run: Run, config: Config, progress: Callable[[int, int], None] | None = None,
             chunk: int = 512, key: jax.Array | None = None,
             prior: PriorMap | None = None,
             on_chunk: Callable[[ChunkReport], None] | None = None) -> SlamResult:
    """Run the filter over a whole Run in chunks of frames (same numbers as one scan).

    Chunking bounds the per-frame outputs held on device and lets ``progress(done, total)``
    and ``on_chunk(ChunkReport)`` (e.g. ``app.viewer``) report; the per-frame PRNG keys are
    fixed up front, so results do not depend on ``chunk``.
    Raises ConfigError when the particle maps would not fit in memory (before allocating
    them), RunError when a local map's observation is not finite in float32
    (``local_observations``) and WeightError, naming the first frame and its local map, when
    an update leaves non-finite weights.

    Map reuse: with a ``prior`` map (``PriorMap``) every particle starts with it, at
    ``prior.start`` (spread by ``prior.start_sigma``), and extends it; the results (paths,
    ``vo_path``, map) are in the prior's frame, on its lattice (``filter_config``).
    """
    if prior is not None:
        run = rebase(run, prior.start)
    cfg = filter_config(config, run, prior)
    params = filter_params(config)
    obs = map_observations(run, config)
    T = run.num_frames
    key = jax.random.key(config.filter.seed) if key is None else key
    keys = rbpf.frame_keys(key, T)
    controls = np.asarray(run.controls, np.float32)
    obs_index = np.asarray(run.obs_index, np.int32)
    chunk = max(1, min(chunk, T))
    pad = (-T) % chunk
    controls = np.concatenate([controls, np.zeros((pad, 3), np.float32)])
    obs_index = np.concatenate([obs_index, -np.ones(pad, np.int32)])
    keys = jnp.concatenate([keys, jax.random.split(jax.random.key(0), pad)]) if pad else keys

    if prior is None:
        state = rbpf.init(cfg, jnp.asarray(run.start_pose(), jnp.float32))
    else:
        state = _prior_state(prior, cfg, key)
    outputs = []
    t0 = time.perf_counter()
    compile_s = hook_s = 0.0
    for start in range(0, T + pad, chunk):
        sl = slice(start, start + chunk)
        c0 = time.perf_counter()
        state, out = rbpf.scan_frames(state, keys[sl], jnp.asarray(controls[sl]),
                                      jnp.asarray(obs_index[sl]), obs, params, cfg)
        out = jax.device_get(out)
        if start == 0:
            compile_s = time.perf_counter() - c0  # first chunk includes compilation
        _check_weights(out[0], start, min(chunk, T - start), obs_index)
        _check_map_status(out[0], start, cfg)
        outputs.append(out)
        if on_chunk is not None:  # its time (e.g. a viewer's logging) is not the filter's
            h0, n = time.perf_counter(), min(chunk, T - start)
            on_chunk(ChunkReport(run, start, jax.tree.map(lambda x: x[:n], out[0]),
                                 out[1][:n], out[2][:n], state, cfg))
            hook_s += time.perf_counter() - h0
        if progress is not None:
            progress(min(start + chunk, T), T)
    seconds = time.perf_counter() - t0 - compile_s - hook_s
    infos = jax.tree.map(lambda *xs: np.concatenate(xs)[:T], *[o[0] for o in outputs])
    best = np.concatenate([o[1] for o in outputs])[:T]
    mean = np.concatenate([o[2] for o in outputs])[:T]
    final_best = int(state.best)
    kmap, smap = rbpf.particle_map(state, final_best, cfg)
    poses, ancestry = jnp.asarray(infos.pose), jnp.asarray(infos.ancestors)
    path = np.asarray(rbpf.backtrack_path(poses, ancestry, jnp.int32(final_best)))
    smoothed = np.asarray(rbpf.smoothed_mean_path(poses, ancestry, state.log_w))
    dropped = int(np.sum(infos.dropped_cells))
    if dropped:  # observed_cells(run) sizes M so that this cannot happen
        raise RuntimeError(f"{dropped} observed local cells did not fit the filter's "
                           f"observed_cells = {cfg.max_observed}")
    violations = int(np.sum(infos.extent_violations))
    if violations:
        warnings.warn(f"{violations} particle updates reached the edge of the "
                      f"{cfg.map_shape} map; observed cells beyond the edge were skipped "
                      f"(neither weighed nor mapped). Increase [map] margin.", ExtentWarning)
    return SlamResult(
        best_path=path, smoothed_path=smoothed, best_pose=best, mean_pose=mean,
        vo_path=run.vo_poses(),
        ess=infos.ess, resampled=infos.resampled, updated=infos.updated, log_lik=infos.log_lik,
        exponent=infos.exponent, kmap=np.asarray(kmap), smap=np.asarray(smap),
        map_origin=cfg.map_origin, resolution=cfg.resolution, extent_violations=violations,
        empty_observations=int(np.sum(infos.empty_obs & infos.updated)), seconds=seconds,
        compile_seconds=compile_s, compile_frames=min(chunk, T), store=cfg.store,
        map_bytes=maps.map_bytes(cfg),
        map_peak_bytes=maps.peak_bytes(state.maps, cfg), estimate=config.filter.estimate)
