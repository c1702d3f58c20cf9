"""A Run's local maps as the filter's observations (k, S) (eq. 13 with the ``[map]``
settings): converted on the host, or kept raw and refined on the device so that the search and
the tuner can vary the settings without a recompilation."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gslam_jax.config import Config, MapSection
from gslam_jax.gridmap.pose_maps import local_cell_centres
from gslam_jax.rbpf import cells
from gslam_jax.run import Run, RunError
from gslam_jax.run.checks import BLOCK_MAPS, describe_cells

__all__ = ["local_observations", "raw_observations", "ObsSettings", "obs_settings",
           "refine_observations", "map_observations", "range_noise_profile", "run_range_noise",
           "RunningRangeNoise", "local_map_footprint", "local_map_footprints"]

RING_M = 0.5          # width of the range rings of ``range_noise_profile``
RING_MIN_CELLS = 200  # a ring with fewer observed cells takes the nearer ring's value
PROFILE_MAPS = 256    # local maps sampled (evenly) for the profile


def local_observations(run: Run, min_variance: float, weight: float = 1.0,
                       min_points: int = 2) -> np.ndarray:
    """[max(M, 1), L, L, 2] float32 observations (k, S) (``cells.obs_from_stats`` with the
    ``[map]`` settings min_variance, obs_weight and min_points); float64 on the host, then cast,
    ``BLOCK_MAPS`` local maps at a time.

    A RunError, naming the local map and a frame that uses it, when a value is not finite in
    float32 (statistics finite in float64 may overflow float32's range, about 3.4e38)."""
    if run.num_local_maps == 0:
        return np.zeros((1, 8, 8, 2), np.float32)
    maps = run.local_maps
    obs = np.empty(maps.shape[:3] + (2,), np.float32)
    with np.errstate(over="ignore", invalid="ignore"):
        for start in range(0, len(maps), BLOCK_MAPS):  # a block's float64 temporaries at a time
            block = slice(start, start + BLOCK_MAPS)
            obs[block] = cells.obs_from_stats(maps[block], min_variance, weight, min_points)
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


def range_noise_profile(obs: np.ndarray, resolution: float) -> np.ndarray:
    """[L * L] float32: the variance (m^2) measurement adds to a cell seen at the range of each
    local cell, estimated from observations ``obs`` [M, L, L, 2] (k, S) of a run.

    Over rings of ``RING_M`` metres of range (from the local map's centre, the robot), the
    median observed variance S / k of the cells with k >= 1; the profile is that median made
    non-decreasing with range, less its value in the nearest ring. The terrain is the same at
    every range on average, so what grows is the measurement's share: stereo depth noise, and
    the blur of a local map fused over metres of travel. A ring with fewer than
    ``RING_MIN_CELLS`` cells takes the nearer ring's value. All zero when no ring has enough
    cells.
    """
    obs = np.asarray(obs, np.float64)
    L = obs.shape[1]
    rng = np.hypot(*local_cell_centres(L, float(resolution))).reshape(-1)
    ring = (rng // RING_M).astype(np.int64)
    k = obs[..., 0].reshape(obs.shape[0], -1)
    S = obs[..., 1].reshape(obs.shape[0], -1)
    seen = k >= 1
    v = np.where(seen, S / np.where(seen, k, 1.0), np.nan)
    rings = int(ring.max()) + 1
    median = np.full(rings, np.nan)
    for r in range(rings):
        vals = v[:, ring == r]
        vals = vals[np.isfinite(vals)]
        if vals.size >= RING_MIN_CELLS:
            median[r] = np.median(vals)
    if not np.isfinite(median).any():
        return np.zeros(L * L, np.float32)
    first = int(np.flatnonzero(np.isfinite(median))[0])
    median[:first] = median[first]
    for r in range(first + 1, rings):  # a sparse ring: the nearer ring's value
        if not np.isfinite(median[r]):
            median[r] = median[r - 1]
    rising = np.maximum.accumulate(median)
    return (rising - rising[0])[ring].astype(np.float32)


def run_range_noise(run: Run, config: Config) -> np.ndarray:
    """``range_noise_profile`` of ``run`` under the config's ``[map]`` settings, from at most
    ``PROFILE_MAPS`` of its local maps, evenly spaced (only those converted)."""
    if run.num_local_maps == 0:
        return np.zeros(run.local_maps.shape[1] ** 2, np.float32)
    pick = np.unique(np.linspace(0, run.num_local_maps - 1,
                                 min(PROFILE_MAPS, run.num_local_maps)).astype(int))
    return range_noise_profile(_profile_observations(run.local_maps[pick], config.map),
                               run.resolution)


def _profile_observations(stats: np.ndarray, m: MapSection) -> np.ndarray:
    """Observations (k, S) [..., 2] in float64 of statistics [..., 3] under the ``[map]``
    settings ``m``, for the profile (a cell not finite here is left out, as its medians skip
    NaN)."""
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        return cells.obs_from_stats(np.asarray(stats, np.float64), m.min_variance, m.obs_weight,
                                    m.min_points)


class RunningRangeNoise:
    """``range_noise_profile`` kept up to date as local maps arrive one at a time, for a filter
    that has no whole run up front (``online.Online``).

    It keeps the observations of at most ``PROFILE_MAPS`` of the maps seen so far, evenly
    spaced: every map until the buffer is full, then every other one kept and every second
    map taken, and so on. The profile is estimated again when the count of maps seen is a power
    of two or a multiple of ``PROFILE_MAPS`` (1, 2, 4, ..., 256, 512, 768, ...), so its cost
    per map stays bounded. It is causal: a map is weighed with the profile of the maps up to
    and including it, where the batch run (``run_range_noise``) uses the maps of the whole run.
    After n maps, n a power of two up to ``PROFILE_MAPS``, the two profiles are equal.
    """

    def __init__(self, config: Config, local_size: int, resolution: float):
        self._map = config.map
        self._resolution = float(resolution)
        self._kept: list[np.ndarray] = []  # [L, L, 2] float64 of maps 0, stride, 2 stride, ...
        self._stride = 1
        self.seen = 0
        self.profile = np.zeros(int(local_size) ** 2, np.float32)

    def add(self, stats: np.ndarray) -> bool:
        """Take the statistics [L, L, 3] (n, sum z, sum z^2) of the next local map; True when
        the profile was estimated again."""
        if self.seen % self._stride == 0:
            self._kept.append(_profile_observations(stats, self._map))
            if len(self._kept) > PROFILE_MAPS:
                self._kept = self._kept[::2]
                self._stride *= 2
        self.seen += 1
        n = self.seen
        if n & (n - 1) == 0 or n % PROFILE_MAPS == 0:
            self.profile = range_noise_profile(np.stack(self._kept), self._resolution)
            return True
        return False


def local_map_footprint(stats: np.ndarray, resolution: float,
                        lattice_heading: float = 0.0) -> np.ndarray:
    """[3] where one local map's statistics [L, L, 3] saw: the centre x, y of its observed
    cells (n > 0) in the robot frame, its lattice turned by ``lattice_heading``
    (``Run.lattice_headings``), and the radius about that centre that holds every observed
    cell whole (m); radius -1 where it saw nothing (``rbpf.factor_cover`` places them)."""
    seen = np.asarray(stats)[:, :, 0] > 0
    if not seen.any():
        return np.array([0.0, 0.0, -1.0])
    cx, cy = local_cell_centres(seen.shape[0], resolution)
    c, s = np.cos(lattice_heading), np.sin(lattice_heading)
    x, y = cx[seen], cy[seen]
    px, py = c * x - s * y, s * x + c * y
    centre = np.array([px.mean(), py.mean()])
    radius = np.sqrt((px - centre[0]) ** 2 + (py - centre[1]) ** 2).max()
    return np.array([centre[0], centre[1], radius + resolution / np.sqrt(2.0)])


def local_map_footprints(run: Run) -> np.ndarray:
    """[T, 3] each frame's ``local_map_footprint``; radius -1 for a frame without a local
    map."""
    out = np.tile([0.0, 0.0, -1.0], (run.num_frames, 1))
    headings = run.lattice_heading_array()
    for t in np.flatnonzero(run.obs_index >= 0):
        m = run.obs_index[t]
        out[t] = local_map_footprint(run.local_maps[m], run.resolution, float(headings[m]))
    return out
