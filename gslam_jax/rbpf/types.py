"""The filter's data: static settings, tunable parameters, the particle set, random numbers and
per-frame outputs (NamedTuple pytrees).

The settings a config file also holds are the config's own (``config.FilterSection``,
``MotionSection``, ``MapSection``): their defaults, their rules (``FilterConfig.validate``) and
the values a ``FilterConfig`` is built with (``FilterConfig.from_config``), one declaration
each.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, NamedTuple

import jax
from jax import Array

from gslam_jax import choices
from gslam_jax.config import Config, FilterSection, MapSection, MotionSection
from gslam_jax.config.sections import SECTION_TYPES
from gslam_jax.config.setting import UNSET, setting_of
from gslam_jax.rbpf import unknown
from gslam_jax.rbpf.motion import MotionParams

__all__ = ["FilterConfig", "FilterParams", "FilterState", "UpdateNoise", "UpdateInfo",
           "StepInfo", "RunOutput", "Observation", "CPU_BLOCK_CELLS", "STORES", "CONFIG_KEYS",
           "GIVEN_FIELDS"]

CPU_BLOCK_CELLS = 102_400  # footprint cells per update pass on CPU (FilterConfig.update_block)
STORES = tuple(s for s in choices.MAP_STORES if s != "auto")  # "auto" is resolved before
DRAWS = tuple(d for d in choices.PROPOSAL_DRAWS if d != "auto")  # likewise


class FilterConfig(NamedTuple):
    """Static settings: shapes and discrete choices (hashable, a jit static argument).

    map_origin is the world (x, y) of the corner of cell (0, 0); cell (i, j) covers
    x in [x0 + i res, x0 + (i+1) res), y likewise with j. map_shape entries are multiples of 8.
    ``from_config`` builds it from a ``Config``'s settings (``CONFIG_KEYS``) and the fields
    the run sizes (``GIVEN_FIELDS``; ``sizing.filter_config``).
    """

    num_particles: int
    map_shape: tuple[int, int]
    map_origin: tuple[float, float]
    resolution: float
    local_size: int
    resampler: str = FilterSection.resampler
    resample_ratio: float = FilterSection.resample_ratio
    unknown_cells: str = FilterSection.unknown_cells
    unknown_samples: int = FilterSection.unknown_samples
    update_map: bool = True    # False: weigh only, never write the maps (tests, diagnostics)
    observed_cells: int = 0    # M, observed local cells one update evaluates (0: L*L)
    particle_block: int = FilterSection.particle_block
    tempering: str = FilterSection.tempering  # "fixed": the paper's beta; "adaptive": ``tempering``
    # "adaptive": conditional ESS fraction kept (``[filter] ess_target = 0`` is resolved by the
    # run's sensor before, ``sizing.extent_filter_config``; this default is a sensorless run's)
    ess_target: float = choices.AUTO_ESS_TARGET["points"]
    store: str = MapSection.store  # "dense" or "shared" (``rbpf.maps``; "auto" resolved before)
    tile: int = MapSection.tile
    pool_tiles: int = MapSection.pool_tiles
    proposal: str = FilterSection.proposal  # "motion" (eq. 24) or "informed" (``proposal``)
    proposal_points: int = FilterSection.proposal_points
    proposal_span: float = FilterSection.proposal_span
    proposal_stages: int = FilterSection.proposal_stages
    proposal_cell_stride: int = FilterSection.proposal_cell_stride
    proposal_exponent: str = FilterSection.proposal_exponent  # "prior" or "normaliser"
    # ``draws.standard_normals`` ("auto" is resolved before, ``sizing.resolve_proposal_draws``;
    # this default is a sensorless run's)
    proposal_draws: str = choices.AUTO_PROPOSAL_DRAWS["points"]
    # > 1: each particle's own factor on the motion stds (``FilterState.noise_scale``)
    noise_spread: float = MotionSection.noise_spread
    # cells from a particle's cell to the farthest cell its observed local cells can land in,
    # sized from the run's local maps for the window store (``maps.resolve_history``; 0: the
    # local map's diagonal, ``reach``)
    observed_reach: int = 0

    @property
    def update_block(self) -> int:
        """Particles per pass of the update's read-weigh-write (``particle_block``; 0: auto).

        Each pass reads a block's footprints, weighs them (eq. 26) and adds the local map to
        them (eq. 14) while they are still in cache. Auto: on a CPU, blocks of about
        ``CPU_BLOCK_CELLS`` footprint cells; on accelerators, one pass over all particles (the
        device wants them all at once). A config built from a ``Config`` (``slam.
        filter_config``) carries the size chosen on the host for the default backend; a
        config built directly with 0 reads the default backend when the update is traced
        (the block size changes the speed; the results agree to float rounding).
        """
        J = self.num_particles
        if self.particle_block:
            return min(self.particle_block, J)
        if jax.default_backend() != "cpu":
            return J
        return max(1, min(J, CPU_BLOCK_CELLS // self.max_observed))

    @property
    def max_observed(self) -> int:
        """M: how many observed local cells one update evaluates (``observed_cells`` or L*L)."""
        return self.observed_cells or self.local_size ** 2

    @property
    def block(self) -> int:
        """Window alignment: bitmask blocks in "sample" mode, single cells otherwise."""
        return unknown.BLOCK if self.unknown_cells == "sample" else 1

    @property
    def reach(self) -> int:
        """Cells from a particle's cell to the farthest map cell its update can touch: every
        local cell centre lies within L / sqrt(2) cells of the particle (``observation_cells``)."""
        return math.ceil(self.local_size / math.sqrt(2.0)) + 1

    @property
    def window(self) -> int:
        """Side of a square global-map window that holds a rotated local map (the minimum map
        side; "sample" mode refreshes its known-cell bits over such a window)."""
        side = 2 * (self.reach + self.block)
        return int(unknown.BLOCK * math.ceil(side / unknown.BLOCK))

    @classmethod
    def from_config(cls, config: Config, **given: Any) -> "FilterConfig":
        """The config's settings by their keys (``CONFIG_KEYS``), with ``given`` over them:
        the ``GIVEN_FIELDS`` the run sizes, and the automatic values resolved on the host
        (``ess_target``, ``proposal_draws``, ``store``)."""
        values = {name: getattr(getattr(config, section), key)
                  for name, (section, key) in CONFIG_KEYS.items()}
        return cls(**{**values, **given})

    def validate(self) -> "FilterConfig":
        """The rule each setting declares (``config.setting``) on the fields taken from the
        config, its automatic value refused (resolved on the host before), then the map's
        shape against the update's window."""
        for name, (section, key) in CONFIG_KEYS.items():
            rule, value = setting_of(SECTION_TYPES[section], key), getattr(self, name)
            if rule.resolved is not UNSET and value == rule.resolved:
                raise ValueError(f"{name} {value!r} is resolved before the filter (by the run's "
                                 "sensor or the machine's memory, ``sizing``)")
            if not rule.allows(value):
                raise ValueError(f"{name} {value!r} {rule.refusal(value)}")
        H, W = self.map_shape
        if H % unknown.BLOCK or W % unknown.BLOCK:
            raise ValueError(f"map_shape {self.map_shape} must be multiples of {unknown.BLOCK}")
        if min(H, W) < self.window:
            raise ValueError(f"map_shape {self.map_shape} is smaller than the update window "
                             f"{self.window} cells")
        if not 0 <= self.observed_reach <= self.reach:
            raise ValueError(f"observed_reach {self.observed_reach} must lie in [0, "
                             f"{self.reach}] (0: the local map's diagonal)")
        if not 0 <= self.observed_cells <= self.local_size ** 2:
            raise ValueError(f"observed_cells {self.observed_cells} must lie in [0, "
                             f"{self.local_size ** 2}] (0: every local cell)")
        return self


def _config_keys() -> dict[str, tuple[str, str]]:
    """FilterConfig field -> (section, key) of the setting it takes: the field of the same name
    in [filter], [map] or [motion], and ``num_particles`` from [filter] particles."""
    keys = {"num_particles": ("filter", "particles")}
    for section in ("filter", "map", "motion"):
        for f in dataclasses.fields(SECTION_TYPES[section]):
            if f.name in FilterConfig._fields:
                keys[f.name] = (section, f.name)
    return keys


CONFIG_KEYS = _config_keys()
"""FilterConfig field -> (section, key) of the config setting it is built from."""

GIVEN_FIELDS = ("map_shape", "map_origin", "local_size", "update_map", "observed_cells",
                "observed_reach")
"""FilterConfig fields no setting holds: sized from the run (or a test's switch)."""


class FilterParams(NamedTuple):
    """The continuous (tunable, differentiable) parameters."""

    motion: MotionParams = MotionParams(MotionSection.alpha_d, MotionSection.alpha_theta_d,
                                        MotionSection.alpha_theta, MotionSection.alpha_cross,
                                        MotionSection.fallback_scale)
    beta_prev: Array | float = FilterSection.beta_prev
    beta_new: Array | float = FilterSection.beta_new
    # [L * L] variance (m^2) that measurement adds to a cell seen at each local cell's range
    # (``observations.range_noise_profile``), added to the map's predicted variance when an
    # observation is weighed (``importance.log_importance``); None: none (the paper)
    range_noise: Array | None = None


class FilterState(NamedTuple):
    """The particle set. Only ``rbpf.maps`` reads, writes and copies ``maps``."""

    pose: Array        # [J, 3]
    log_w: Array       # [J] normalised
    maps: Any          # the particles' maps (``maps.Maps``): ``densestore.DenseMaps`` or
                       # ``tilestore.TileStore``
    best: Array        # [] int32: slot of the highest-weight particle (``kernel.best_slot``):
                       # after a resampling, the one that was best before it (the weights are
                       # then all equal)
    prior_cov: Array | None = None  # [J, 3, 3] "informed" proposal: the motion covariance
                                    # accumulated since each particle's last update (else None)
    noise_scale: Array | None = None  # [J] each particle's factor on the motion stds
                                      # (``cfg.noise_spread`` > 1; else None: all 1)


class UpdateNoise(NamedTuple):
    """Random numbers of one update: unknown-cell choices and resampling uniforms."""

    unknown_u: Array   # [J, unknown_samples] uniforms ([J, 0] in "ignore" mode)
    resample_u: Array  # [J]
    proposal_z: Array | None = None  # [J, 3] standard normals of the "informed" proposal


class Observation(NamedTuple):
    """The observed cells of one local map, compacted (paper 6.3: compute where it matters).

    The first ``count`` entries are the cells with k > 0 in row-major order; the rest are
    padding (index 0, k = S = 0) up to the static length M = ``cfg.max_observed``.
    """

    index: Array    # [M] int32 flat local cell index a * L + b
    k: Array        # [M]
    S: Array        # [M]
    dropped: Array  # observed cells that did not fit in M (0 when M is large enough)
    # [] the local map's lattice against the robot frame, radians (``Run.lattice_headings``)
    lattice_heading: Array | float = 0.0


class UpdateInfo(NamedTuple):
    """What ``update`` (weigh, write, normalise) reports besides the new state."""

    ess: Array           # ESS after the weight update, before any resampling (eq. 23)
    log_lik: Array       # log mean weight increment (log marginal likelihood term)
    extent_violations: Array  # particles with observed local cells outside the map extent
    empty_obs: Array     # bool: the local map had no informative cell
    dropped_cells: Array  # observed local cells beyond cfg.max_observed (0 when M suffices)
    exponent: Array      # exponent applied to the log importance factors (1: the paper's beta)


class StepInfo(NamedTuple):
    """Per-frame outputs of ``step`` (stacked to [T, ...] by ``run_filter``)."""

    pose: Array          # [J, 3] after resampling
    ancestors: Array     # [J] index of each particle's parent before this frame's resampling
    best: Array          # [] slot of the highest-weight particle (FilterState.best)
    log_w: Array         # [J] normalised weights after the frame
    ess: Array           # ESS after the weight update, before resampling (eq. 23)
    resampled: Array     # bool
    updated: Array       # bool: the frame carried a local map
    log_lik: Array       # log mean weight increment (log marginal likelihood term), 0 if none
    extent_violations: Array  # particles with observed local cells outside the map extent
    empty_obs: Array     # bool: the local map had no informative cell
    dropped_cells: Array  # observed local cells beyond cfg.max_observed (0 when M suffices)
    map_status: Array    # [] int32 the shared store's sticky error bits (0: fine; dense: 0),
                         # raised on the host by ``maps.check_status``
    exponent: Array      # exponent applied to the update's log importance factors (1: the
                         # paper's fixed beta or no update; < 1: adaptive tempering flattened them)
    map_free: Array      # [] int32 free tiles in the shared store's pool at the frame's end
                         # (dense: 0); ``run_slam`` grows an automatic pool from it
    noise_scale: Array   # [] the particles' factor on the motion stds, weighted geometric
                         # mean after the frame (``FilterState.noise_scale``; 1: none)


class RunOutput(NamedTuple):
    """What ``run_filter`` returns."""

    final_state: FilterState
    infos: StepInfo         # stacked per frame: pose [T, J, 3], ancestors [T, J], ess [T], ...
    best_pose: Array        # [T, 3] highest-weight particle at each frame
    mean_pose: Array        # [T, 3] weighted mean (circular mean for theta)
    best_path: Array        # [T, 3] path of the final best particle, through its ancestry
