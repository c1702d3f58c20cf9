"""Designs: the points of a search space to evaluate (grid, random, Halton, Sobol)."""

from __future__ import annotations

import math
import warnings

import numpy as np
from scipy.stats import qmc

from gslam_jax import choices
from gslam_jax.tuning.space import SearchError, SearchSpace

__all__ = ["DESIGNS", "DesignNotice", "unit_points", "design_points"]

DESIGNS = choices.SEARCH_DESIGNS


def unit_points(design: str, n: int, dim: int, seed: int = 0) -> np.ndarray:
    """``n`` points in [0, 1)^dim: ``sobol`` and ``halton`` from ``scipy.stats.qmc``, scrambled
    with ``seed`` (Owen scrambling / random permutations: no point on the cube's corner, and a
    reproducible design per seed), or ``random`` (uniform). Sobol's balance needs n = 2^m; other
    n take the first n points of the next power of two."""
    if design == "random":
        return np.random.default_rng(seed).uniform(size=(n, dim))
    if design == "sobol":
        m = max(0, math.ceil(math.log2(n)))
        return qmc.Sobol(dim, scramble=True, seed=seed).random_base2(m)[:n]
    if design == "halton":
        return qmc.Halton(dim, scramble=True, seed=seed).random(n)
    raise SearchError(f"design '{design}' has no unit points; choose sobol, halton or random")


class DesignNotice(UserWarning):
    """A grid design evaluates fewer sets than asked for (n is not a d-th power)."""


def design_points(space: SearchSpace, design: str, n: int, seed: int = 0) -> np.ndarray:
    """Parameter values [P, d] of a design: ``grid`` (m points per axis with m^d <= n,
    axis end points included), ``random`` (uniform, or log-uniform on log axes), ``halton`` or
    ``sobol`` (scrambled quasi-random, ``unit_points``); ``seed`` picks the draw."""
    if design not in DESIGNS:
        raise SearchError(f"design '{design}' unknown; choose one of {', '.join(DESIGNS)}")
    if not isinstance(n, (int, np.integer)) or n < 1:
        raise SearchError(f"n must be a positive integer, got {n!r}")
    d = space.dim
    if design == "grid":
        m = max(1, int(math.floor(n ** (1.0 / d) + 1e-9)))
        if m ** d != n:
            warnings.warn(f"design 'grid': {m} point{'s' if m > 1 else ''} per axis over {d} "
                          f"parameters gives {m ** d} set{'s' if m ** d > 1 else ''}, not the "
                          f"{n} asked for (a grid needs n = m^{d}; use n = {(m + 1) ** d} "
                          f"for {m + 1} per axis, or another design)", DesignNotice,
                          stacklevel=2)
        axis = np.linspace(0.0, 1.0, m) if m > 1 else np.array([0.5])
        unit = np.stack(np.meshgrid(*([axis] * d), indexing="ij"), -1).reshape(-1, d)
    else:
        unit = unit_points(design, n, d, seed)
    return space.scale(unit)
