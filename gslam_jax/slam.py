"""Running Gamma-SLAM on a Run: the chunked scan of the filter over its frames, the checks of
what each chunk returns, and the results.

This is the host-side driver the CLI, the experiments and the benchmarks share. The filter math
lives in ``rbpf``; the settings for a Run in ``sizing``, its observations in ``observations``,
map reuse in ``map_reuse``, the axes of the map's lattice in ``map_axes`` (``map_heading``,
``on_map_axes``, ``LatticeWarning`` and ``local_lattice_axes`` are exported here too).
"""

from __future__ import annotations

import time
import warnings
from typing import Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from gslam_jax import rbpf
from gslam_jax.config import Config
from gslam_jax.errors import ArgumentError, InputError, integer_argument
from gslam_jax.gridmap import GridMap, turn_poses
from gslam_jax.map_axes import (LatticeWarning, check_local_lattices, local_lattice_axes,
                                map_heading, on_map_axes)
from gslam_jax.map_reuse import PriorMap, prior_state, rebase
from gslam_jax.observations import (ObsSettings, local_map_footprints, map_observations,
                                    obs_settings, raw_observations)
from gslam_jax.rbpf import maps, tilestore
from gslam_jax.run import Run, known_positions
from gslam_jax.sizing import fallback_frames, filter_config, filter_params, map_memory

__all__ = ["RunArrays", "run_arrays", "ground_truth_mask", "require_ground_truth", "SlamResult",
           "run_slam", "ExtentWarning", "WeightError", "ChunkReport", "map_heading",
           "on_map_axes", "filtered_run", "run_filter_config", "LatticeWarning",
           "local_lattice_axes"]


class ExtentWarning(UserWarning):
    """Particles observed cells outside the map extent (those cells were skipped)."""


class WeightError(InputError):
    """The filter cannot weigh the data: an update left non-finite particle weights (ESS or
    log-likelihood not finite); names the frame and the local map."""


class RunArrays(NamedTuple):
    """A Run's device arrays, as the batched search and the tuner feed them to the filter."""

    controls: jax.Array    # [T, 3]
    obs_index: jax.Array   # [T]
    local_obs: jax.Array   # [M, L, L, 2] raw observations (``raw_observations``)
    lattice_headings: jax.Array  # [M] (``Run.lattice_heading_array``)
    reference: jax.Array   # [T, 3] ground truth (zeros where unknown)
    mask: jax.Array        # [T] frames with a ground-truth position (``ground_truth_mask``)
    start: jax.Array       # [3]
    obs: ObsSettings       # the config's settings for ``refine_observations``
    fallback: jax.Array | None = None  # [T] bool (``sizing.fallback_frames``; None: none)
    footprints: jax.Array | None = None  # [T, 3] (``observations.local_map_footprints``)


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


def run_arrays(run: Run, config: Config, varied: Sequence[str] = (),
               error: type[InputError] = InputError) -> tuple[RunArrays, rbpf.FilterConfig]:
    """Device arrays of ``run`` (raw observations, to be refined on the device with the
    config's or searched settings) and the static filter config for it; the start pose and
    the reference on the map lattice's axes (``map_heading``; the errors against the
    reference do not depend on them). ``varied``: the settings a search or the tuner varies;
    with ``fallback_scale`` among them the fallback frames' flags are kept even at a scale of
    1 (``sizing.fallback_frames``), and a run without such frames is an ``error``."""
    run = filtered_run(run, config)[2]
    keep_fallback = "fallback_scale" in varied
    fallback = fallback_frames(run, config, keep=keep_fallback)
    if keep_fallback and fallback is None:
        raise error("fallback_scale scales the motion noise of the frames whose control came "
                    "from the fallback odometry (Run.vo_failed), and this run has none: it "
                    "would change nothing; leave it out")
    T = run.num_frames
    gt = run.ground_truth if run.ground_truth is not None else np.full((T, 3), np.nan)
    arrays = RunArrays(
        controls=jnp.asarray(run.controls, jnp.float32),
        obs_index=jnp.asarray(run.obs_index, jnp.int32),
        local_obs=jnp.asarray(raw_observations(run)),
        lattice_headings=jnp.asarray(run.lattice_heading_array()),
        reference=jnp.asarray(np.nan_to_num(gt), jnp.float32),
        mask=jnp.asarray(ground_truth_mask(run)),
        start=jnp.asarray(run.start_pose(), jnp.float32),
        obs=obs_settings(config),
        fallback=None if fallback is None else jnp.asarray(fallback),
        footprints=jnp.asarray(local_map_footprints(run), jnp.float32))
    return arrays, filter_config(config, run)


def filtered_run(run: Run, config: Config, prior: PriorMap | None = None
                 ) -> tuple[Run, float, Run]:
    """``run`` as given (rebased on a ``prior``'s start), the angle of the map lattice's axes
    in its frame (``map_heading``) and the run on those axes (``on_map_axes``): what
    ``run_slam`` filters."""
    if prior is not None:
        run = rebase(run, prior.start)
    heading = map_heading(run, config, prior)
    return run, heading, on_map_axes(run, heading)


def run_filter_config(run: Run, config: Config, prior: PriorMap | None = None
                      ) -> rbpf.FilterConfig:
    """The static filter config ``run_slam`` runs ``run`` with (sized on the map lattice's
    axes, ``filtered_run``), e.g. for ``online.Online(filter_config=...)`` to reproduce it."""
    return filter_config(config, filtered_run(run, config, prior)[2], prior)


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


def _scan_chunk(state: rbpf.FilterState, start: int, frames: tuple, obs: jax.Array,
                headings: jax.Array, params: rbpf.FilterParams, cfg: rbpf.FilterConfig,
                growth: maps.PoolGrowth | None) -> tuple[rbpf.FilterState, tuple,
                                                          rbpf.FilterConfig]:
    """``rbpf.scan_frames`` over one chunk of ``frames`` (keys, controls, obs_index,
    fallback flags or None) from frame ``start`` (local maps ``obs`` on lattices turned by
    ``headings``), its outputs on the host. With an automatic pool (``growth``) the chunk is run
    again from its start, in a grown pool, when it ran out of tiles (as long as the memory
    allows; otherwise its outputs carry the status that ``_check_map_status`` names)."""
    keys, controls, obs_index, fallback = frames

    def scan(s: rbpf.FilterState, cfg: rbpf.FilterConfig) -> tuple[rbpf.FilterState, tuple]:
        return rbpf.scan_frames(s, keys, controls, obs_index, obs, params, cfg, headings,
                                fallback)

    if growth is None:
        state, out = scan(state, cfg)
        return state, jax.device_get(out), cfg
    growth.before(state.maps)
    kept = jax.tree.map(jnp.copy, state)  # scan_frames donates the state it is given
    while True:
        state, out = scan(state, cfg)
        out = jax.device_get(out)
        ran_out = _ran_out(out[0])
        regrown = ran_out and growth.regrow(kept.maps, cfg, start, start + ran_out - 1)
        if not regrown:
            return state, out, cfg
        kept, cfg = kept._replace(maps=regrown[0]), regrown[1]
        growth.before(kept.maps)
        state = jax.tree.map(jnp.copy, kept)


def _ran_out(info: rbpf.StepInfo) -> int:
    """1 + the chunk frame at which the shared pool first ran out of tiles; 0 if it did not."""
    status = np.asarray(info.map_status)
    hit = (status & tilestore.POOL_EXHAUSTED) != 0
    return int(np.argmax(hit)) + 1 if hit.any() else 0


def _check_map_status(info: rbpf.StepInfo, start: int, cfg: rbpf.FilterConfig,
                      automatic: bool = False) -> None:
    """The map store's error (``maps.check_status``) at the first frame it flagged;
    ``automatic``: the pool is grown by a ``maps.PoolGrowth``."""
    status = np.asarray(info.map_status)
    if status.any():
        i = int(np.argmax(status != 0))
        maps.check_status(status[i], cfg, where=f"frame {start + i}: ", automatic=automatic)


class SlamResult(NamedTuple):
    """Host-side (NumPy) outputs of one Gamma-SLAM run."""

    best_path: np.ndarray      # [T, 3] the final best particle's path through its ancestry
    map_path: np.ndarray       # [T, 3] the path of the particle whose map kmap is
    #                            (``rbpf.map_particle``): mode_path under estimate "mode"
    #                            or "mode_mean", else best_path
    smoothed_path: np.ndarray  # [T, 3] final-weighted mean of every final particle's ancestry
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
    steps_path: np.ndarray | None = None  # [T, 3] the smoother's mean steps, composed
    mode_path: np.ndarray | None = None   # [T, 3] the final densest particle's ancestral path
    mode_mean_path: np.ndarray | None = None  # [T, 3] the smoother's mean over its 1 m
    #                                           neighbourhood (``rbpf.mode_mean_path``)
    local_steps_path: np.ndarray | None = None  # [T, 3] mean steps, each weighed by the
    #                                             factors that bear on it (``rbpf.local_step_path``)
    noise_scale: np.ndarray | None = None  # [T] the particles' factor on the motion stds after
    #                                        each frame, weighted geometric mean (all 1 unless
    #                                        [motion] noise_spread > 1)

    @property
    def path(self) -> np.ndarray:
        """[T, 3] the reported trajectory ([filter] estimate): ``best_path``, ``mean_pose``,
        ``smoothed_path``, ``steps_path``, ``mode_path``, ``mode_mean_path`` or
        ``local_steps_path``."""
        return {"best": self.best_path, "mean": self.mean_pose, "smoothed": self.smoothed_path,
                "steps": self.steps_path, "mode": self.mode_path,
                "mode_mean": self.mode_mean_path,
                "local_steps": self.local_steps_path}[self.estimate]

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

    The filter runs on the map lattice's axes (``map_heading``); the paths are turned back
    into the run's frame and the map keeps its axes (``SlamResult.map_heading``). A prior's
    start spread is drawn on its lattice's axes. An ArgumentError names a ``run``, ``config``
    or ``chunk`` of the wrong type.
    """
    if not isinstance(run, Run):
        raise ArgumentError(f"run_slam: run must be a gslam_jax.Run (load_run(path), "
                            f"simulate_run(...)[0]), got {type(run).__name__}")
    if not isinstance(config, Config):
        raise ArgumentError(f"run_slam: config must be a gslam_jax.Config (Config(), or "
                            f"load_config(path)), got {type(config).__name__}")
    integer_argument(chunk, "run_slam: chunk", 1)
    given, heading, run = filtered_run(run, config, prior)
    check_local_lattices(given, heading)
    cfg = filter_config(config, run, prior)
    params = filter_params(config, run)
    obs = map_observations(run, config)
    headings = jnp.asarray(run.lattice_heading_array())
    T = run.num_frames
    key = jax.random.key(config.filter.seed) if key is None else key
    keys = rbpf.frame_keys(key, T)
    controls = np.asarray(run.controls, np.float32)
    obs_index = np.asarray(run.obs_index, np.int32)
    chunk = max(1, min(chunk, T))
    pad = (-T) % chunk
    controls = np.concatenate([controls, np.zeros((pad, 3), np.float32)])
    obs_index = np.concatenate([obs_index, -np.ones(pad, np.int32)])
    fallback = fallback_frames(run, config)
    if fallback is not None:
        fallback = np.concatenate([fallback, np.zeros(pad, bool)])
    keys = jnp.concatenate([keys, jax.random.split(jax.random.key(0), pad)]) if pad else keys

    if prior is None:
        state = rbpf.init(cfg, jnp.asarray(run.start_pose(), jnp.float32))
    else:
        state = prior_state(prior._replace(start=run.start_pose()), cfg, key)
    outputs = []
    available, what = map_memory()
    # an automatic pool keeps a copy of each chunk's start to run it again if it runs out:
    # two pools live at once, so each may take half the memory
    growth = maps.PoolGrowth.automatic(cfg, config.map.pool_tiles, available // 2, what)
    t0 = time.perf_counter()
    compile_s = hook_s = 0.0
    for start in range(0, T + pad, chunk):
        sl = slice(start, start + chunk)
        c0 = time.perf_counter()
        frames = (keys[sl], jnp.asarray(controls[sl]), jnp.asarray(obs_index[sl]),
                  None if fallback is None else jnp.asarray(fallback[sl]))
        state, out, cfg = _scan_chunk(state, start, frames, obs, headings, params, cfg,
                                      growth)
        if start == 0:
            compile_s = time.perf_counter() - c0  # first chunk includes compilation
        _check_weights(out[0], start, min(chunk, T - start), obs_index)
        _check_map_status(out[0], start, cfg, automatic=growth is not None)
        outputs.append(out)
        if on_chunk is not None:  # its time (e.g. a viewer's logging) is not the filter's
            h0, n = time.perf_counter(), min(chunk, T - start)
            on_chunk(ChunkReport(run, start, jax.tree.map(lambda x: x[:n], out[0]),
                                 out[1][:n], out[2][:n], state, cfg, heading))
            hook_s += time.perf_counter() - h0
        if progress is not None:
            progress(min(start + chunk, T), T)
        if growth is not None and start + chunk < T:
            grown, cfg = growth.after(state.maps, cfg, out[0].map_free, start + chunk)
            state = state._replace(maps=grown)
    seconds = time.perf_counter() - t0 - compile_s - hook_s
    infos = jax.tree.map(lambda *xs: np.concatenate(xs)[:T], *[o[0] for o in outputs])
    best = np.concatenate([o[1] for o in outputs])[:T]
    mean = np.concatenate([o[2] for o in outputs])[:T]
    poses, ancestry = jnp.asarray(infos.pose), jnp.asarray(infos.ancestors)
    map_slot = rbpf.map_particle(config.filter.estimate, poses[-1], state.log_w, state.best)
    kmap, smap = rbpf.particle_map(state, map_slot, cfg)
    path = np.asarray(rbpf.backtrack_path(poses, ancestry, state.best))
    map_path = np.asarray(rbpf.backtrack_path(poses, ancestry, map_slot))
    smoothed = np.asarray(rbpf.smoothed_mean_path(poses, ancestry, state.log_w))
    steps = np.asarray(rbpf.smoothed_step_path(poses, ancestry, state.log_w))
    densest = rbpf.densest_particle(poses[-1], state.log_w)  # once for both mode estimates
    mode = np.asarray(rbpf.backtrack_path(poses, ancestry, densest))
    mode_mean = np.asarray(rbpf.mode_mean_path(poses, ancestry, state.log_w, densest))
    local_steps = np.asarray(rbpf.ancestry_path(
        "local_steps", poses, ancestry, state.log_w, state.best,
        rbpf.step_history(infos.log_w, infos.resampled, mean, local_map_footprints(run))))
    dropped = int(np.sum(infos.dropped_cells))
    if dropped:  # observed_cells(run) sizes M so that this cannot happen
        raise RuntimeError(f"{dropped} observed local cells did not fit the filter's "
                           f"observed_cells = {cfg.max_observed}")
    violations = int(np.sum(infos.extent_violations))
    if violations:
        warnings.warn(f"{violations} particle updates reached the edge of the "
                      f"{cfg.map_shape} map; observed cells beyond the edge were skipped "
                      f"(neither weighed nor mapped). Increase [map] margin.", ExtentWarning)
    def back(poses: np.ndarray) -> np.ndarray:  # the run's frame
        return turn_poses(poses, heading)

    return SlamResult(
        best_path=back(path), map_path=back(map_path), smoothed_path=back(smoothed),
        best_pose=back(best),
        mean_pose=back(mean), vo_path=given.vo_poses(),
        ess=infos.ess, resampled=infos.resampled, updated=infos.updated, log_lik=infos.log_lik,
        exponent=infos.exponent, noise_scale=infos.noise_scale, kmap=np.asarray(kmap),
        smap=np.asarray(smap),
        map_origin=cfg.map_origin, resolution=cfg.resolution, extent_violations=violations,
        empty_observations=int(np.sum(infos.empty_obs & infos.updated)), seconds=seconds,
        compile_seconds=compile_s, compile_frames=min(chunk, T), store=cfg.store,
        map_bytes=maps.map_bytes(cfg),
        map_peak_bytes=maps.peak_bytes(state.maps, cfg), estimate=config.filter.estimate,
        map_heading=heading, steps_path=back(steps), mode_path=back(mode),
        mode_mean_path=back(mode_mean), local_steps_path=back(local_steps))
