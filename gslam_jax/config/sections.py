"""The settings: one frozen dataclass per TOML section, with the paper's values as defaults,
and ``Config.validate``, whose errors name the source, section and key. Enumerated settings
take their allowed values from ``choices``."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from gslam_jax import choices
from gslam_jax.errors import InputError

__all__ = ["ConfigError", "FilterSection", "MotionSection", "MapSection", "LocalMapSection",
           "StereoSection", "RigSection", "Config", "SECTION_TYPES"]


class ConfigError(InputError):
    """A configuration problem; the message names the file, section and key."""


@dataclass(frozen=True)
class FilterSection:
    """Particle filter (paper 6.1-6.2)."""

    particles: int = 200
    resampler: str = "multinomial"
    resample_ratio: float = 0.5
    # eq. 30 ("ignore"), as the paper ran the Mars Yard courses; "sample" is eq. 31 (an unknown
    # cell scored against a random known cell), which closes long loops more often but was no
    # better on the simulator's courses (it broke one of five default maze runs) and is 2-3x
    # slower per run (docs/results.md, "Unknown cells: eq. 30 against eq. 31").
    unknown_cells: str = "ignore"
    unknown_samples: int = 1024
    beta_prev: float = 0.05
    beta_new: float = 0.05
    # "fixed": every update's log importance factors tempered by beta alone, as in the paper;
    # "adaptive": also by the largest exponent <= 1 that keeps the conditional ESS of the
    # update at ess_target * J (adaptive SMC, gslam_jax/rbpf/tempering.py). Adaptive
    # is the default: the paper's beta collapsed the particles on real stereo, and on the
    # simulated Table I courses adaptive was within 2% of fixed or better (docs/results.md)
    tempering: str = "adaptive"
    # 0: automatic, by how the run's local maps were made (``choices.AUTO_ESS_TARGET``): 0.5
    # for the simulator's point sensor, 0.99 for stereo, whose correlated cells make eq. 26
    # overconfident (0.5 resampled at every update on KITTI and rendered stereo, and the
    # filter was worse than VO-only with the default motion noise; docs/real-data.md)
    ess_target: float = 0.0
    # the reported trajectory (slam.SlamResult.path): "best", the final best particle's path
    # through its ancestry (the paper); "mean", each frame's weighted mean pose (filtering);
    # "smoothed", the final weights' mean over every final particle's ancestral path (the
    # default until 2026-12-05); "steps", the path of those paths' mean steps
    # (rbpf.smoothed_step_path; the default until 2026-12-06): the same on the simulator's
    # Table I (within 0.3 mm), but where the particles' headings spread under stereo's flat
    # weights the smoothed path comes out shorter than any particle's, a scale error that made
    # most of the KITTI clip's gain over VO-only (docs/real-data.md, "What the gain over VO is
    # made of"); "mode", the ancestral path of the final particle with the most weight within
    # 1 m; "mode_mean", the smoother's mean over the final particles within 1 m of that one
    # (rbpf.mode_mean_path); "local_steps" (default), the mean steps each weighed only by the
    # factors of the updates whose maps reach back to it (rbpf.local_step_path): "steps" to
    # 0.1 mm on Table I, where resampling leaves few factors to split; on stereo's flat
    # weights it drops the Monte Carlo error of the others (docs/real-data.md, "Where the
    # seeds' spread comes from")
    estimate: str = "local_steps"
    # "motion": each particle's pose drawn from the motion model alone (eq. 24, the paper);
    # "informed": at a local map, drawn from a Gaussian fitted to its map score times its
    # motion prior, with the exact importance weight (rbpf/proposal.py)
    proposal: str = "motion"
    proposal_points: int = 3    # "informed": candidates per axis of each grid (odd)
    proposal_span: float = 2.0  # "informed": half-width of the first grid, in prior stds
    proposal_stages: int = 2    # "informed": grids, each in the previous fit's coordinates
    # "informed": the fit scores every n-th observed cell (as GMapping's lskip skips beams in
    # its scan matching); the weights always use every cell
    proposal_cell_stride: int = 1
    # "informed" with adaptive tempering: the exponent keeps the conditional ESS of the scores
    # spread over the motion prior ("prior") or of each particle's normaliser ("normaliser":
    # only the spread the proposal leaves in the weights; rbpf/tempering.py)
    proposal_exponent: str = "prior"
    # the proposals' standard normals: "independent" per particle (the paper), or "antithetic"
    # pairs (particle j + ceil(J/2) moves by the negated draw of particle j), so that where the
    # weights are flat the particles' mean heading is the VO's; "auto": by the run's sensor,
    # antithetic for stereo, independent for the simulator's point sensor
    # (choices.AUTO_PROPOSAL_DRAWS; why: docs/real-data.md)
    proposal_draws: str = "auto"
    # "none": eq. 26 as in the paper; "profile": a cell seen from afar has the measurement
    # variance of its range added to what its map cell predicts (observations.
    # range_noise_profile, from the run's own local maps; rbpf.importance)
    range_noise: str = "none"
    seed: int = 0
    # particles per pass of the update's read-weigh-write; 0: automatic (cache-sized blocks on
    # a CPU, all particles on an accelerator; resolved on the host, sizing.filter_config)
    particle_block: int = 0


@dataclass(frozen=True)
class MotionSection:
    """VO error constants of eqs. 2-3, the cross-track one, and the fallback odometry's scale
    on them (``rbpf.motion``)."""

    alpha_d: float = 0.05
    alpha_theta_d: float = 0.01
    alpha_theta: float = 0.05
    # cross-track std per metre travelled (rbpf.motion); 0: the paper's eq. 1, which has none
    alpha_cross: float = 0.0
    # every std above times this on frames whose control came from the fallback odometry
    # (Run.vo_failed: wheels and IMU where VO failed, "less accurate than those from VO",
    # paper 4); 1: weighed as VO
    fallback_scale: float = 1.0
    # The particles' own motion noise: each particle's stds are the ones above times its own
    # factor, spread over (1 / noise_spread, noise_spread) at the start, half of them near 1,
    # and resampled with it, so the filter weighs noise levels as it weighs poses
    # (rbpf.motion.particle_scales); 1: every particle the alphas above (the paper)
    noise_spread: float = 1.0


@dataclass(frozen=True)
class MapSection:
    """Global variance grid map."""

    resolution: float = 0.16
    margin: float = 10.0
    min_variance: float = 1e-6
    # degrees of freedom per local-map cell as a fraction of n - 1 (cells.obs_from_stats)
    obs_weight: float = 1.0
    min_points: int = 2  # heights a local-map cell needs to be used (at least 2)
    # Particle map storage: "dense" (a whole map per particle), "shared" (copy-on-write tiles
    # of tile x tile cells in a pool of pool_tiles tiles; 0: sized automatically) or "auto"
    # (dense when it fits in memory, shared otherwise); rbpf.tilestore. "window": each
    # particle's map as its path over the shared local maps plus a window of cells around it
    # (rbpf.windowstore; tile: cells a particle may move between local maps, pool_tiles: the
    # local maps its history holds, 0: the run's; eq. 30 only).
    store: str = "dense"
    tile: int = 32
    pool_tiles: int = 0
    # The lattice's axes: the robot's at its start pose ("start": the filter runs on those axes
    # and turns its paths back; the map keeps them, map.npz's heading), so the result does not
    # depend on the angle of the frame the run is given in; or the frame's ("frame": the
    # paper's, and the default before; e.g. a map on a GPS frame's axes). choices.MAP_AXES
    axes: str = "start"


@dataclass(frozen=True)
class LocalMapSection:
    """Local-map observations (paper 6.3); see localmap.LocalMapParams."""

    max_range: float = 10.0
    min_height: float = -2.0
    max_height: float = 2.0
    travel: float = 2.0
    cells: int = 0
    lattice: str = "auto"


def _given_keys(section: object) -> list[str]:
    """A section's keys set to other than 0 or empty (the source's own), in declaration
    order."""
    return [f.name for f in dataclasses.fields(section) if getattr(section, f.name)]


@dataclass(frozen=True)
class StereoSection:
    """Dense stereo of the image sources (sim-stereo, kitti, euroc; vo.stereo.DenseStereoParams).
    0 or "" keeps the source's own setting (64 disparities, KITTI 128; block 5; stride 2;
    "sgbm"; every point, whatever its depth error; 0.25 px of disparity noise; points at depth
    edges dropped where a 5 x 5 window spans over half the pixel's disparity)."""

    num_disparities: int = 0
    block: int = 0
    stride: int = 0
    algorithm: str = ""
    max_depth_error: float = 0.0
    disparity_std: float = 0.0
    edge_ratio: float = 0.0

    def is_default(self) -> bool:
        return self == StereoSection()

    def given(self) -> list[str]:
        """The keys set (not 0 or empty), in declaration order."""
        return _given_keys(self)


@dataclass(frozen=True)
class RigSection:
    """The camera mount of the image sources (kitti, euroc, sim-stereo, stereo;
    ``datasets.mount.camera_mount``): the left camera on the robot (x forward, y left, z up,
    origin on the ground under the robot). ``height`` (m, camera above the ground), ``pitch``
    (deg, nose down positive), ``roll`` (deg, about the forward axis, right side down
    positive), ``yaw`` (deg, left positive), ``forward`` and ``lateral`` (m, robot x and y);
    or ``matrix``, the full 4x4 camera-to-robot transform (16 numbers, or 4 rows of 4), not
    both. 0 or empty keeps the source's own value (KITTI: 1.65 m, level)."""

    height: float = 0.0
    pitch: float = 0.0
    roll: float = 0.0
    yaw: float = 0.0
    forward: float = 0.0
    lateral: float = 0.0
    matrix: tuple[float, ...] = ()

    def is_default(self) -> bool:
        return self == RigSection()

    def given(self) -> list[str]:
        """The keys set (not 0 or empty), in declaration order."""
        return _given_keys(self)

    def check(self) -> tuple[str, str] | None:
        """(key, problem) of the first bad value, or None."""
        if not self.height >= 0:
            return "height", "must be >= 0 (0: the source's own)"
        for key, limit in (("pitch", 90.0), ("roll", 180.0), ("yaw", 180.0)):
            if not abs(getattr(self, key)) <= limit:
                return key, f"must be in [-{limit:g}, {limit:g}] degrees (0: the source's own)"
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

        Every float must be finite (TOML accepts ``inf`` and ``nan``), then meet its range.
        """
        for name in SECTION_TYPES:
            section = getattr(self, name)
            for key, value in dataclasses.asdict(section).items():
                if isinstance(value, float) and not math.isfinite(value):
                    raise ConfigError(f"{source}: [{name}] {key} must be finite, got {value}")
        f, m, lm, st = self.filter, self.map, self.localmap, self.stereo
        checks = [
            (f.particles >= 1, "filter", "particles", "must be at least 1"),
            (f.resampler in choices.RESAMPLERS, "filter", "resampler",
             f"must be one of {', '.join(choices.RESAMPLERS)}"),
            (0.0 <= f.resample_ratio <= 1.0, "filter", "resample_ratio", "must be in [0, 1]"),
            (f.unknown_cells in choices.UNKNOWN_CELLS, "filter", "unknown_cells",
             f"must be one of {', '.join(choices.UNKNOWN_CELLS)} (eq. 30, eq. 31)"),
            (f.unknown_samples >= 1, "filter", "unknown_samples", "must be at least 1"),
            (f.beta_prev > 0, "filter", "beta_prev", "must be positive"),
            (f.beta_new > 0, "filter", "beta_new", "must be positive"),
            (f.tempering in choices.TEMPERING, "filter", "tempering",
             f"must be one of {', '.join(choices.TEMPERING)} (the paper's beta, or an "
             "ESS-targeted exponent on it)"),
            (0.0 <= f.ess_target <= 1.0, "filter", "ess_target",
             "must be in [0, 1] (0: automatic by the run's sensor)"),
            (f.estimate in choices.ESTIMATES, "filter", "estimate",
             f"must be one of {', '.join(choices.ESTIMATES)} (final best particle's path, "
             "each frame's weighted mean pose, the smoother's mean path or mean steps, the "
             "path of the final cloud's densest particle, the smoother's mean over its "
             "1 m neighbourhood, or mean steps each weighed by the factors that bear on it)"),
            (f.proposal in choices.PROPOSALS, "filter", "proposal",
             f"must be one of {', '.join(choices.PROPOSALS)} (the motion model alone, or "
             "informed by the local map)"),
            (f.proposal_points >= 1 and f.proposal_points % 2 == 1, "filter",
             "proposal_points", "must be odd and >= 1 (1: the prior itself)"),
            (f.proposal_span > 0, "filter", "proposal_span", "must be positive"),
            (f.proposal_stages >= 1, "filter", "proposal_stages", "must be at least 1"),
            (f.proposal_cell_stride >= 1, "filter", "proposal_cell_stride", "must be at least 1"),
            (f.proposal_exponent in choices.PROPOSAL_EXPONENTS, "filter", "proposal_exponent",
             f"must be one of {', '.join(choices.PROPOSAL_EXPONENTS)} (the score's spread over "
             "the prior, or each particle's normaliser's)"),
            (f.proposal_draws in choices.PROPOSAL_DRAWS, "filter", "proposal_draws",
             f"must be one of {', '.join(choices.PROPOSAL_DRAWS)}"),
            (f.range_noise in choices.RANGE_NOISE, "filter", "range_noise",
             f"must be one of {', '.join(choices.RANGE_NOISE)}"),
            (0 <= f.seed < 2 ** 32, "filter", "seed", f"must be in [0, 2**32), got {f.seed}"),
            (f.particle_block >= 0, "filter", "particle_block", "must be >= 0 (0: automatic)"),
            *((getattr(self.motion, k) >= 0, "motion", k, "must be non-negative")
              for k in ("alpha_d", "alpha_theta_d", "alpha_theta", "alpha_cross")),
            (0 < self.motion.fallback_scale <= 1000, "motion", "fallback_scale",
             "must be in (0, 1000] (1: the fallback's frames weighed as VO's)"),
            (1 <= self.motion.noise_spread <= 1000, "motion", "noise_spread",
             "must be in [1, 1000] (1: every particle the alphas given)"),
            (m.resolution > 0, "map", "resolution", "must be positive"),
            (m.margin >= 0, "map", "margin", "must be non-negative"),
            # S = 0 with k > 0 would make log S = -inf and every log weight NaN
            (m.min_variance > 0, "map", "min_variance", "must be positive (a floor of S / k)"),
            (m.obs_weight > 0, "map", "obs_weight", "must be positive"),
            (m.min_points >= 2, "map", "min_points", "must be at least 2"),
            (m.store in choices.MAP_STORES, "map", "store",
             f"must be one of {', '.join(choices.MAP_STORES)}"),
            (m.tile >= 8 and m.tile % 8 == 0, "map", "tile", "must be a positive multiple of 8"),
            (m.pool_tiles >= 0, "map", "pool_tiles", "must be >= 0 (0: automatic)"),
            (m.axes in choices.MAP_AXES, "map", "axes",
             f"must be one of {', '.join(choices.MAP_AXES)} (the run's frame's axes, or the "
             "robot's at its start)"),
            (lm.max_range > 0, "localmap", "max_range", "must be positive"),
            (lm.min_height < lm.max_height, "localmap", "min_height", "must be below max_height"),
            (lm.travel > 0, "localmap", "travel", "must be positive"),
            (lm.lattice in choices.LOCALMAP_LATTICES, "localmap", "lattice",
             f"must be one of {', '.join(choices.LOCALMAP_LATTICES)} (the robot's axes, the "
             "map's at the VO pose, or by the sensor)"),
            (lm.cells >= 0 and lm.cells % 2 == 0, "localmap", "cells", "must be even and >= 0"),
            (st.num_disparities >= 0 and st.num_disparities % 16 == 0, "stereo",
             "num_disparities", "must be a multiple of 16 (0: the source's default)"),
            (st.block == 0 or (st.block >= 1 and st.block % 2 == 1), "stereo", "block",
             "must be odd (0: the source's default)"),
            (st.stride >= 0, "stereo", "stride", "must be >= 0 (0: the source's default)"),
            (st.max_depth_error >= 0, "stereo", "max_depth_error",
             "must be >= 0 (0: the source's default)"),
            (st.edge_ratio >= 0, "stereo", "edge_ratio", "must be >= 0 (0: the source's default)"),
            (0 <= st.disparity_std <= 4, "stereo", "disparity_std",
             "must be in [0, 4] px (0: the source's default; SGBM's is 0.1-1 px)"),
            (st.algorithm in ("", *choices.STEREO_ALGORITHMS), "stereo", "algorithm",
             f"must be one of {', '.join(choices.STEREO_ALGORITHMS)} (\"\": the source's "
             "default)"),
        ]
        for ok, section, key, msg in checks:
            if not ok:
                raise ConfigError(f"{source}: [{section}] {key} {msg}")
        bad = self.rig.check()
        if bad is not None:
            raise ConfigError(f"{source}: [rig] {bad[0]} {bad[1]}")
        return self


SECTION_TYPES = {"filter": FilterSection, "motion": MotionSection, "map": MapSection,
                  "localmap": LocalMapSection, "stereo": StereoSection, "rig": RigSection}
