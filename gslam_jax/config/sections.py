"""The settings: one frozen dataclass per TOML section, each field a setting declared once
(``setting``: default, one-line meaning, rule, the paper's value where the default differs),
and ``Config.validate``, whose errors name the source, section and key. Enumerated settings
take their allowed values from ``choices``; why each default is what it is:
docs/appendix/settings-rationale.md."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from gslam_jax import choices
from gslam_jax.config.setting import UNSET, setting, settings_of
from gslam_jax.errors import InputError

__all__ = ["ConfigError", "FilterSection", "MotionSection", "MapSection", "LocalMapSection",
           "StereoSection", "RigSection", "Config", "SECTION_TYPES", "paper_differences"]


class ConfigError(InputError):
    """A configuration problem; the message names the file, section and key."""


def _at_least(low: int) -> Callable[[Any], bool]:
    return lambda v: v >= low


def _positive(v: float) -> bool:
    return v > 0


def _non_negative(v: float) -> bool:
    return v >= 0


@dataclass(frozen=True)
class FilterSection:
    """Particle filter (paper 6.1-6.2)."""

    particles: int = setting(200, "J, the number of particles", _at_least(1),
                             "must be at least 1")
    resampler: str = setting("multinomial", "resampling scheme (multinomial: the paper's)",
                             one_of=choices.RESAMPLERS)
    resample_ratio: float = setting(0.5, "resample when the ESS < resample_ratio * J (eq. 23)",
                                    lambda v: 0.0 <= v <= 1.0, "must be in [0, 1]")
    unknown_cells: str = setting(
        "ignore", "cells a particle's map does not know: ignore (eq. 30, the paper's) or "
        "sample (eq. 31: scored against a random known cell of its map)",
        one_of=choices.UNKNOWN_CELLS, note="eq. 30, eq. 31")
    unknown_samples: int = setting(1024, "sample: known-cell draws per particle per update",
                                   _at_least(1), "must be at least 1")
    beta_prev: float = setting(0.05, "tempering of the map's prior cells (eqs. 29-31)",
                               _positive, "must be positive")
    beta_new: float = setting(0.05, "tempering of the new observation (eqs. 29-31)",
                              _positive, "must be positive")
    tempering: str = setting(
        "adaptive", "fixed: the log importance factors tempered by beta alone (the paper); "
        "adaptive: also by the largest exponent <= 1 that keeps the update's conditional ESS "
        "at ess_target * J (rbpf.tempering)", one_of=choices.TEMPERING,
        note="the paper's beta, or an ESS-targeted exponent on it", paper="fixed")
    ess_target: float = setting(
        0.0, "adaptive: the conditional-ESS fraction each update keeps; 0: automatic by the "
        "run's sensor (" + ", ".join(f"{v:g} for {k}" for k, v in
                                     choices.AUTO_ESS_TARGET.items()) + ")",
        lambda v: 0.0 <= v <= 1.0, "must be in [0, 1] (0: automatic by the run's sensor)",
        resolved=0.0)
    estimate: str = setting(
        "local_steps", "the reported trajectory: best (the final best particle's path, the "
        "paper), mean (each frame's weighted mean), smoothed (the smoother's mean path), steps "
        "(its mean steps), mode (the densest final particle's path), mode_mean (the smoother's "
        "mean within 1 m of it), local_steps (mean steps each weighed by the updates that bear "
        "on it)", one_of=choices.ESTIMATES,
        note="final best particle's path, each frame's weighted mean pose, the smoother's mean "
        "path or mean steps, the path of the final cloud's densest particle, the smoother's "
        "mean over its 1 m neighbourhood, or mean steps each weighed by the factors that bear "
        "on it", paper="best")
    proposal: str = setting(
        "motion", "motion: each pose drawn from the motion model alone (eq. 24, the paper); "
        "informed: at a local map, from a Gaussian fitted to its map score times its motion "
        "prior (rbpf.proposal)", one_of=choices.PROPOSALS,
        note="the motion model alone, or informed by the local map")
    proposal_points: int = setting(
        3, "informed: candidates per axis of each scoring grid (odd; 1: the prior itself)",
        lambda v: v >= 1 and v % 2 == 1, "must be odd and >= 1 (1: the prior itself)")
    proposal_span: float = setting(
        2.0, "informed: half-width of the first grid, in standard deviations of the prior",
        _positive, "must be positive")
    proposal_stages: int = setting(
        2, "informed: grids scored, each in the coordinates of the previous fit",
        _at_least(1), "must be at least 1")
    proposal_cell_stride: int = setting(
        1, "informed: the grids score every n-th observed cell (the weights use every cell)",
        _at_least(1), "must be at least 1")
    proposal_exponent: str = setting(
        "prior", "informed with adaptive tempering: the exponent keeps the conditional ESS of "
        "the scores over the motion prior (prior) or of each particle's normaliser (normaliser)",
        one_of=choices.PROPOSAL_EXPONENTS,
        note="the score's spread over the prior, or each particle's normaliser's")
    proposal_draws: str = setting(
        "auto", "the proposals' standard normals: independent per particle (the paper) or "
        "antithetic pairs; auto: by the run's sensor (" + ", ".join(
            f"{v} for {k}" for k, v in choices.AUTO_PROPOSAL_DRAWS.items()) + ")",
        one_of=choices.PROPOSAL_DRAWS, resolved="auto", paper="independent")
    range_noise: str = setting(
        "none", "none: eq. 26 as in the paper; profile: the measurement variance of a cell's "
        "range, estimated from the run's local maps, added to what its map cell predicts",
        one_of=choices.RANGE_NOISE)
    seed: int = setting(0, "PRNG seed of the filter", lambda v: 0 <= v < 2 ** 32,
                        "must be in [0, 2**32), got {value}")
    particle_block: int = setting(
        0, "particles per pass of the update's read-weigh-write; 0: automatic (cache-sized "
        "blocks on a CPU, all particles on an accelerator)", _non_negative,
        "must be >= 0 (0: automatic)")


@dataclass(frozen=True)
class MotionSection:
    """VO error constants of eqs. 2-3, the cross-track one, and the fallback odometry's scale
    on them (``rbpf.motion``)."""

    alpha_d: float = setting(0.05, "along-track noise std per metre travelled (eq. 2)",
                             _non_negative, "must be non-negative")
    alpha_theta_d: float = setting(0.01, "heading noise std, rad per metre travelled (eq. 3)",
                                   _non_negative, "must be non-negative")
    alpha_theta: float = setting(0.05, "heading noise std per radian turned (eq. 3)",
                                 _non_negative, "must be non-negative")
    alpha_cross: float = setting(
        0.0, "cross-track noise std per metre travelled; 0: none, the paper's eq. 1",
        _non_negative, "must be non-negative")
    fallback_scale: float = setting(
        1.0, "every std above times this on frames whose control came from the fallback "
        "odometry (Run.vo_failed); 1: weighed as VO", lambda v: 0 < v <= 1000,
        "must be in (0, 1000] (1: the fallback's frames weighed as VO's)")
    noise_spread: float = setting(
        1.0, "> 1: each particle its own factor on the stds above, spread over "
        "(1 / noise_spread, noise_spread) and resampled with it; 1: every particle the alphas "
        "above (the paper)", lambda v: 1 <= v <= 1000,
        "must be in [1, 1000] (1: every particle the alphas given)")


@dataclass(frozen=True)
class MapSection:
    """Global variance grid map."""

    resolution: float = setting(0.16, "cell side, metres (a Run file's must equal it)",
                                _positive, "must be positive")
    margin: float = setting(10.0, "metres added around the VO path's extent for drift",
                            _non_negative, "must be non-negative")
    # S = 0 with k > 0 would make log S = -inf and every log weight NaN
    min_variance: float = setting(1e-6, "floor of S / k, m^2", _positive,
                                  "must be positive (a floor of S / k)")
    obs_weight: float = setting(
        1.0, "degrees of freedom per local-map cell as a fraction of n - 1 (1: independent "
        "heights, the paper; cells.obs_from_stats)", _positive, "must be positive")
    min_points: int = setting(2, "heights a local-map cell needs to be used (at least 2)",
                              _at_least(2), "must be at least 2")
    store: str = setting(
        "dense", "particle maps: dense (a whole map per particle), shared (copy-on-write tiles "
        "in one pool), window (each particle's path over the shared local maps plus a window "
        "of cells around it; eq. 30 only) or auto (dense when it fits in memory, else shared)",
        one_of=choices.MAP_STORES, resolved="auto")
    tile: int = setting(32, "shared store: tile side, cells (a multiple of 8); window store: "
                        "cells a particle may move between local maps",
                        lambda v: v >= 8 and v % 8 == 0, "must be a positive multiple of 8")
    pool_tiles: int = setting(0, "shared store: tiles in the pool; window store: local maps "
                              "its history holds; 0: automatic (grown as the run needs, or the "
                              "run's local maps)", _non_negative, "must be >= 0 (0: automatic)")
    axes: str = setting(
        "start", "the map lattice's axes: start (the robot's at its start pose, the result "
        "independent of the run frame's angle) or frame (the run frame's, the paper's)",
        one_of=choices.MAP_AXES, note="the run's frame's axes, or the robot's at its start",
        paper="frame")


@dataclass(frozen=True)
class LocalMapSection:
    """Local-map observations (paper 6.3); see localmap.LocalMapParams."""

    max_range: float = setting(10.0, "range gate, metres (the paper: 5 or 10)", _positive,
                               "must be positive")
    min_height: float = setting(-2.0, "lowest point height kept, metres (below max_height)")
    max_height: float = setting(2.0, "highest point height kept, metres; points above are "
                                "overhangs")
    travel: float = setting(2.0, "metres of travel fused into one local map", _positive,
                            "must be positive")
    cells: int = setting(0, "local map side, cells (even); 0: the smallest multiple of 8 "
                         "covering max_range", lambda v: v >= 0 and v % 2 == 0,
                         "must be even and >= 0")
    lattice: str = setting(
        "auto", "the axes local maps are binned on: robot (the robot's, the paper's), map (the "
        "map's at the VO pose) or auto (by the sensor: " + ", ".join(
            f"{v} for {k}" for k, v in choices.AUTO_LOCALMAP_LATTICE.items()) + ")",
        one_of=choices.LOCALMAP_LATTICES,
        note="the robot's axes, the map's at the VO pose, or by the sensor", paper="robot")


def _given_keys(section: object) -> list[str]:
    """A section's keys set to other than 0 or empty (the source's own), in declaration
    order."""
    return [f.name for f in dataclasses.fields(section) if getattr(section, f.name)]


@dataclass(frozen=True)
class StereoSection:
    """Dense stereo of the image sources (sim-stereo, kitti, euroc;
    vo.stereo.DenseStereoParams). 0 or "" keeps the source's own setting."""

    num_disparities: int = setting(
        0, "dense stereo search range, pixels (a multiple of 16); 0: the source's (64; KITTI "
        "128)", lambda v: v >= 0 and v % 16 == 0,
        "must be a multiple of 16 (0: the source's default)")
    block: int = setting(0, "SGBM window side, pixels (odd); 0: the source's (5)",
                         lambda v: v == 0 or (v >= 1 and v % 2 == 1),
                         "must be odd (0: the source's default)")
    stride: int = setting(0, "every stride-th pixel made a point; 0: the source's (2)",
                          _non_negative, "must be >= 0 (0: the source's default)")
    algorithm: str = setting(
        "", "stereo matcher, " + " or ".join(choices.STEREO_ALGORITHMS) + "; \"\": the "
        "source's (sgbm)", lambda v: v in ("", *choices.STEREO_ALGORITHMS),
        f"must be one of {', '.join(choices.STEREO_ALGORITHMS)} (\"\": the source's default)")
    max_depth_error: float = setting(
        0.0, "metres: no point whose depth error (to first order in the measured disparity "
        "noise) exceeds it; 0: the source's (no limit)", _non_negative,
        "must be >= 0 (0: the source's default)")
    disparity_std: float = setting(
        0.0, "pixels of disparity noise max_depth_error assumes until measured; 0: the "
        "source's (0.25)", lambda v: 0 <= v <= 4,
        "must be in [0, 4] px (0: the source's default; SGBM's is 0.1-1 px)")
    edge_ratio: float = setting(
        0.0, "no point of a pixel whose 5 x 5 disparities span more than this fraction of its "
        "own (depth edges); 0: the source's (0.5)", _non_negative,
        "must be >= 0 (0: the source's default)")

    def is_default(self) -> bool:
        return self == StereoSection()

    def given(self) -> list[str]:
        """The keys set (not 0 or empty), in declaration order."""
        return _given_keys(self)


@dataclass(frozen=True)
class RigSection:
    """The camera mount of the image sources (kitti, euroc, sim-stereo, stereo;
    ``datasets.mount.camera_mount``): the left camera on the robot (x forward, y left, z up,
    origin on the ground under the robot), by its values or by ``matrix``, not both. 0 or
    empty keeps the source's own value (KITTI: 1.65 m, level)."""

    height: float = setting(0.0, "metres of the camera above the ground; 0: the source's own",
                            _non_negative, "must be >= 0 (0: the source's own)")
    pitch: float = setting(0.0, "degrees, nose down positive, in [-90, 90]; 0: the source's "
                           "own", lambda v: abs(v) <= 90,
                           "must be in [-90, 90] degrees (0: the source's own)")
    roll: float = setting(0.0, "degrees about the forward axis, right side down positive; 0: "
                          "the source's own", lambda v: abs(v) <= 180,
                          "must be in [-180, 180] degrees (0: the source's own)")
    yaw: float = setting(0.0, "degrees, left positive; 0: the source's own",
                         lambda v: abs(v) <= 180,
                         "must be in [-180, 180] degrees (0: the source's own)")
    forward: float = setting(0.0, "metres along the robot's x axis; 0: the source's own")
    lateral: float = setting(0.0, "metres along the robot's y axis, left positive; 0: the "
                             "source's own")
    matrix: tuple[float, ...] = setting(
        (), "the full 4x4 camera-to-robot transform, 4 rows of 4, instead of the values above; "
        "[]: the source's own")

    def is_default(self) -> bool:
        return self == RigSection()

    def given(self) -> list[str]:
        """The keys set (not 0 or empty), in declaration order."""
        return _given_keys(self)

    def check(self) -> tuple[str, str] | None:
        """(key, problem) of the first bad value the keys' own rules do not catch (the matrix
        against the values, and as a rigid transform), or None."""
        if not self.matrix:
            return None
        others = [k for k in self.given() if k != "matrix"]
        if others:
            return "matrix", (f"and {', '.join(others)} are exclusive: give the full 4x4 or "
                              "the values, not both")
        m = np.array(self.matrix, float).reshape(4, 4)
        if not np.all(np.isfinite(m)):
            return "matrix", "must be finite"
        if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
            return "matrix", f"bottom row must be [0, 0, 0, 1], got {m[3].tolist()}"
        r = m[:3, :3]
        if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
            return "matrix", "rotation part is not a rotation (R R^T != I or det < 0)"
        return None


@dataclass(frozen=True)
class Config:
    filter: FilterSection = field(default_factory=FilterSection)
    motion: MotionSection = field(default_factory=MotionSection)
    map: MapSection = field(default_factory=MapSection)
    localmap: LocalMapSection = field(default_factory=LocalMapSection)
    stereo: StereoSection = field(default_factory=StereoSection)
    rig: RigSection = field(default_factory=RigSection)

    def validate(self, source: str = "<config>") -> "Config":
        """Check every value; a ConfigError names the source, section and key at fault.

        Every float must be finite (TOML accepts ``inf`` and ``nan``), then meet the rule its
        setting declares, then the rules between keys (the height band, the rig's matrix).
        """
        for name in SECTION_TYPES:
            section = getattr(self, name)
            for key, value in dataclasses.asdict(section).items():
                if isinstance(value, float) and not math.isfinite(value):
                    raise ConfigError(f"{source}: [{name}] {key} must be finite, got {value}")
        for name in SECTION_TYPES:
            section = getattr(self, name)
            for key, _, rule in settings_of(section):
                value = getattr(section, key)
                if not rule.allows(value):
                    raise ConfigError(f"{source}: [{name}] {key} {rule.refusal(value)}")
        if not self.localmap.min_height < self.localmap.max_height:
            raise ConfigError(f"{source}: [localmap] min_height must be below max_height")
        bad = self.rig.check()
        if bad is not None:
            raise ConfigError(f"{source}: [rig] {bad[0]} {bad[1]}")
        return self


SECTION_TYPES = {"filter": FilterSection, "motion": MotionSection, "map": MapSection,
                  "localmap": LocalMapSection, "stereo": StereoSection, "rig": RigSection}


def paper_differences() -> dict[str, tuple[Any, Any]]:
    """``"section.key"`` -> (default, the paper's value) of every setting whose default is not
    the paper's (``configs/paper.toml`` holds the paper's), in declaration order."""
    return {f"{name}.{key}": (default, rule.paper)
            for name, cls in SECTION_TYPES.items()
            for key, default, rule in settings_of(cls) if rule.paper is not UNSET}
