"""Map reuse (``gslam run --prior-map``): a finished map the particles start with, where the
run starts in it, and how the filter starts from it."""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gslam_jax import rbpf
from gslam_jax.config import Config, ConfigError
from gslam_jax.gridmap import GridMap, place
from gslam_jax.rbpf import maps
from gslam_jax.run import Run
from gslam_jax.run.checks import check_start_pose

__all__ = ["PriorMap", "START_STREAM", "check_prior", "check_start_reaches",
           "locate_prior_start", "rebase",
           "known_box", "prior_state"]

START_STREAM = 0x57A7  # folded into the filter's key for the start poses drawn around a prior


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


def check_prior(prior: PriorMap, config: Config) -> None:
    """ConfigError when the prior map cannot be the filter's map: another resolution than
    [map] resolution (the filter's grid lies on the prior's lattice), or a start pose or
    spread that is not finite (the spread must be >= 0), or a start beyond float32's reach of
    the map's cells (``run.checks.check_start_pose``)."""
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
    from gslam_jax.gridmap.relocalise import locate_start

    found = locate_start(prior.grid, run)
    given = np.asarray(prior.start_sigma, float)
    sigma = given if np.any(given > 0) else found.sigma
    located = {"frames": found.frames, **found.alignment.summary()}
    prior = prior._replace(start=found.start, start_sigma=sigma, located=located)
    check_prior(prior, config)
    return prior


def check_start_reaches(prior: PriorMap, run: Run) -> None:
    """ConfigError when ``run``'s VO path, started at ``prior.start``, never comes within a
    local map's reach (half its diagonal) of the box around the prior's known cells: the run
    would never see the prior map, and the result would be two disjoint maps. A prior without
    known cells, or without a start yet, is not checked."""
    box = known_box(prior.grid)
    if box is None or prior.start is None or run.local_maps.shape[0] == 0:
        return
    lo, hi = box
    reach = run.local_maps.shape[1] * float(run.resolution) * math.sqrt(2.0) / 2.0
    xy = rebase(run, prior.start).vo_poses()[:, :2]
    c, s = math.cos(prior.grid.heading), math.sin(prior.grid.heading)
    lattice = xy @ np.array([[c, -s], [s, c]])  # R(heading)^T p: the map's lattice axes
    gap = np.linalg.norm(np.maximum(np.maximum(lo - lattice, lattice - hi), 0.0), axis=1)
    if gap.min() > reach:
        x, y, th = (float(v) for v in prior.start)
        turned = f" on its lattice's axes, turned {prior.grid.heading:.3f} rad" if c != 1 else ""
        raise ConfigError(
            f"--start {x:g},{y:g},{th:g}: this run's VO path, started there, comes no nearer "
            f"than {gap.min():.1f} m to the prior map's known cells (x {lo[0]:.1f} to "
            f"{hi[0]:.1f} m, y {lo[1]:.1f} to {hi[1]:.1f} m{turned}), beyond a local map's "
            f"reach of {reach:.1f} m: the run would never see the prior map. Give --start in the "
            f"prior map's frame (or leave it out to locate the start)")


def rebase(run: Run, start: np.ndarray) -> Run:
    """``run`` starting at ``start`` (a pose in another frame, e.g. a prior map's): its VO path
    (``Run.vo_poses``) and everything the filter does are then in that frame."""
    return run._replace(initial_pose=np.asarray(start, np.float64).copy())


def known_box(grid: GridMap) -> tuple[np.ndarray, np.ndarray] | None:
    """(lo, hi) corners of the box around the prior's known cells; None when it has none."""
    i, j = np.nonzero(grid.known)
    if not i.size:
        return None
    r, o = grid.resolution, np.asarray(grid.origin, np.float64)
    return (o + r * np.array([i.min(), j.min()]), o + r * np.array([i.max() + 1, j.max() + 1]))


def prior_state(prior: PriorMap, cfg: rbpf.FilterConfig, key: jax.Array) -> rbpf.FilterState:
    """The filter's start with a prior map: the prior placed on the filter's grid in every
    particle's map, the particles at ``prior.start`` spread by ``prior.start_sigma`` (drawn
    from ``key`` folded with START_STREAM; a zero spread draws nothing)."""
    grid = place(prior.grid, cfg.map_origin, cfg.map_shape)
    if cfg.store == "shared":
        need, have = maps.prior_tiles(grid.k, cfg), maps.pool_tiles(cfg)
        if need > have:
            raise ConfigError(f"the prior map needs {need} tiles of the shared map store, "
                              f"more than its [map] pool_tiles = {have}; raise [map] "
                              "pool_tiles (0: automatic)")
    sigma = np.asarray(prior.start_sigma, np.float64)
    return rbpf.init(cfg, jnp.asarray(prior.start, jnp.float32),
                     (jnp.asarray(grid.k, jnp.float32), jnp.asarray(grid.S, jnp.float32)),
                     jax.random.fold_in(key, START_STREAM),
                     jnp.asarray(sigma, jnp.float32) if sigma.any() else None)
