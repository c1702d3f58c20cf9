"""The searchable settings and the search space over them.

``SETTINGS`` is the one table of the continuous settings that the search and the tuner vary:
where each lives in ``Config``, what values it takes, and how it reaches the device. Every
other list of names (``PARAM_NAMES``, the filter parameters, the observation settings, the
tuner's), the base values of a config, the config holding searched values and the checks of a
``[space]`` range are derived from it.

Two routes to the device, both traced (no recompilation per value):

* filter parameters (``[motion]`` alphas of eqs. 2-3 and the fallback odometry's scale on
  them, ``[filter]`` betas of eqs. 29-31): fields of ``rbpf.FilterParams``
  (``params_from_values``);
* observation settings (``[map]`` min_variance, obs_weight, min_points): fields of
  ``observations.ObsSettings``, applied to the run's raw observations on the device by
  ``observations.refine_observations`` (``observations_from_values``), as in a plain run.

Other config values are shapes or discrete choices (static: a recompilation per value) or
belong to the front-end (they change the Run); they are not searchable.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from pathlib import Path
from typing import Any, NamedTuple, Sequence

import jax.numpy as jnp
import numpy as np
from jax import Array

from gslam_jax import rbpf
from gslam_jax.config import Config, ConfigError
from gslam_jax.driver import observations
from gslam_jax.errors import InputError

__all__ = ["Setting", "SETTINGS", "PARAM_NAMES", "FILTER_PARAM_NAMES", "OBS_PARAM_NAMES",
           "MOTION_PARAM_NAMES", "ALPHA_NAMES", "TUNABLE_NAMES", "SearchError", "SearchSpace",
           "parse_space", "load_space", "params_from_values", "observations_from_values",
           "base_values", "config_with_values"]


class SearchError(InputError):
    """A bad search space, design or objective; the message names the field."""


class Setting(NamedTuple):
    """One searchable setting. ``name`` is both its field in ``Config.<section>`` and its key
    in ``[space]``; a filter parameter (``[motion]``: ``FilterParams.motion``; ``[filter]``:
    ``FilterParams``) or an observation setting (``[map]``: ``observations.ObsSettings``)."""

    name: str
    section: str            # "motion", "filter" or "map"
    positive: bool = False  # values must be above ``minimum`` (else at or above it)
    minimum: float = 0.0
    integer: bool = False   # the config holds an int: the threshold n >= ceil(value)
    why: str = ""           # why ``minimum``, for the error message
    # a ratio of the motion noise's stds (fallback_scale), not a std: kept when the noise is
    # widened as a whole (``evidence_fit``), and tuned only when named
    ratio: bool = False

    @property
    def observation(self) -> bool:
        """An observation setting (refined on the device), not a filter parameter."""
        return self.section == "map"


_SETTINGS = (
    Setting("alpha_d", "motion"),
    Setting("alpha_theta_d", "motion"),
    Setting("alpha_theta", "motion"),
    Setting("alpha_cross", "motion"),
    Setting("fallback_scale", "motion", positive=True, ratio=True),
    Setting("beta_prev", "filter", positive=True),
    Setting("beta_new", "filter", positive=True),
    Setting("min_variance", "map", positive=True),
    Setting("obs_weight", "map", positive=True),
    Setting("min_points", "map", minimum=2.0, integer=True,
            why="a cell needs two heights for a variance"),
)
SETTINGS: dict[str, Setting] = {s.name: s for s in _SETTINGS}
PARAM_NAMES = tuple(SETTINGS)
FILTER_PARAM_NAMES = tuple(s.name for s in _SETTINGS if not s.observation)
OBS_PARAM_NAMES = tuple(s.name for s in _SETTINGS if s.observation)
MOTION_PARAM_NAMES = tuple(s.name for s in _SETTINGS if s.section == "motion")
ALPHA_NAMES = tuple(s.name for s in _SETTINGS if s.section == "motion" and not s.ratio)
TUNABLE_NAMES = tuple(s.name for s in _SETTINGS if not s.integer)  # thresholds: no gradient


class SearchSpace(NamedTuple):
    """Named ranges. lo/hi are in parameter units; ``log`` marks a log-uniform axis."""

    names: tuple[str, ...]
    lo: tuple[float, ...]
    hi: tuple[float, ...]
    log: tuple[bool, ...]

    @property
    def dim(self) -> int:
        return len(self.names)

    def scale(self, unit: np.ndarray) -> np.ndarray:
        """Points in [0, 1]^d -> parameter values [P, d] (float64)."""
        unit = np.asarray(unit, np.float64)
        lo, hi = np.asarray(self.lo), np.asarray(self.hi)
        lg = np.asarray(self.log)
        lin = lo + unit * (hi - lo)
        with np.errstate(divide="ignore", invalid="ignore"):
            logv = np.exp(np.log(lo) + unit * (np.log(hi) - np.log(lo)))
        return np.where(lg, logv, lin)


def _check_range(setting: Setting, lo: Any, hi: Any, log: bool, source: str
                 ) -> tuple[float, float]:
    where = f"{source}: [space] {setting.name}"
    for v in (lo, hi):
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise SearchError(f"{where}: range bounds must be numbers, got {v!r}")
    lo, hi = float(lo), float(hi)
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise SearchError(f"{where}: range [{lo}, {hi}] must be finite")
    if lo > hi:
        raise SearchError(f"{where}: inverted range [{lo}, {hi}] (lower bound above upper)")
    if lo == hi:
        raise SearchError(f"{where}: empty range [{lo}, {hi}]; fix the value in the config "
                          f"instead of searching it")
    if setting.minimum > 0 and lo < setting.minimum:
        raise SearchError(f"{where}: range [{lo}, {hi}] must start at {setting.minimum:g} or "
                          f"above ({setting.why})")
    if lo < setting.minimum or (setting.positive and lo <= setting.minimum):
        raise SearchError(f"{where}: range [{lo}, {hi}] must be "
                          f"{'positive' if setting.positive else 'non-negative'}")
    if log and lo <= 0:
        raise SearchError(f"{where}: a log-scale range needs a positive lower bound, got {lo}")
    return lo, hi


def parse_space(table: dict[str, Any], source: str = "<space>") -> SearchSpace:
    """Build a SearchSpace from a ``[space]`` table.

    Each entry is ``name = [lo, hi]`` (linear) or ``name = {range = [lo, hi], log = true}``.
    """
    if not isinstance(table, dict) or not table:
        raise SearchError(f"{source}: [space] must be a non-empty table of name = [lo, hi]")
    names, los, his, logs = [], [], [], []
    for name, spec in table.items():
        if name not in SETTINGS:
            raise SearchError(f"{source}: [space] unknown parameter '{name}'; searchable "
                              f"parameters: {', '.join(PARAM_NAMES)}")
        log = False
        if isinstance(spec, dict):
            extra = set(spec) - {"range", "log"}
            if extra:
                raise SearchError(f"{source}: [space] {name}: unknown key(s) {sorted(extra)}; "
                                  f"expected range and log")
            log = spec.get("log", False)
            if not isinstance(log, bool):
                raise SearchError(f"{source}: [space] {name}: log must be true or false")
            spec = spec.get("range")
        if not isinstance(spec, (list, tuple)) or len(spec) != 2:
            raise SearchError(f"{source}: [space] {name}: expected a range [lo, hi], got {spec!r}")
        lo, hi = _check_range(SETTINGS[name], spec[0], spec[1], log, source)
        names.append(name), los.append(lo), his.append(hi), logs.append(log)
    return SearchSpace(tuple(names), tuple(los), tuple(his), tuple(logs))


def load_space(path: str | Path) -> tuple[SearchSpace, dict[str, Any]]:
    """Read a search TOML file: ``[space]`` (required) and ``[search]`` options (optional:
    design, n, objective, path, seed). Returns the space and the options dict."""
    path = Path(path)
    if not path.exists():
        raise SearchError(f"{path}: no such search-space file")
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as err:
        raise SearchError(f"{path}: malformed TOML: {err}") from err
    unknown = set(data) - {"space", "search"}
    if unknown:
        raise SearchError(f"{path}: unknown section(s) {sorted(unknown)}; expected [space] and "
                          f"[search]")
    if "space" not in data:
        raise SearchError(f"{path}: missing [space] table")
    options = dict(data.get("search", {}))
    allowed = {"design": str, "n": int, "objective": str, "path": str, "seed": int}
    for key, value in options.items():
        if key not in allowed:
            raise SearchError(f"{path}: [search] unknown key '{key}'; known keys: "
                              f"{', '.join(allowed)}")
        if not isinstance(value, allowed[key]) or isinstance(value, bool):
            raise SearchError(f"{path}: [search] {key}: expected {allowed[key].__name__}, "
                              f"got {value!r}")
    return parse_space(data["space"], str(path)), options


def params_from_values(values: Array, names: Sequence[str], base: rbpf.FilterParams
                       ) -> rbpf.FilterParams:
    """FilterParams whose named fields take the columns of ``values`` [..., d]; the other
    filter parameters are broadcast from ``base``."""
    batch = values.shape[:-1]
    col = {n: values[..., i] for i, n in enumerate(names)}

    def pick(section: str, fields: NamedTuple) -> dict[str, Array]:
        return {s.name: col[s.name] if s.name in col else
                jnp.broadcast_to(jnp.asarray(getattr(fields, s.name), values.dtype), batch)
                for s in _SETTINGS if s.section == section}

    return base._replace(motion=base.motion._replace(**pick("motion", base.motion)),
                         **pick("filter", base))


def observations_from_values(values: Array, names: Sequence[str], base: observations.ObsSettings,
                             raw: Array) -> Array:
    """Local-map observations [M, L, L, 2] for one parameter row ``values`` [d]: the raw
    observations (``device_arrays.run_arrays``) refined by
    ``observations.refine_observations`` with the named observation settings, the others from
    ``base``."""
    col = {n: values[i] for i, n in enumerate(names)}
    settings = base._replace(**{n: col[n] for n in OBS_PARAM_NAMES if n in col})
    return observations.refine_observations(raw, settings)


def base_values(config: Config) -> dict[str, float]:
    """Every searchable setting's value in ``config``."""
    return {s.name: float(getattr(getattr(config, s.section), s.name)) for s in _SETTINGS}


def config_with_values(config: Config, values: dict[str, float]) -> Config:
    """``config`` with searched/tuned values set (an integer setting: the threshold
    n >= ceil(value) that the search applied), checked by ``Config.validate``."""
    changes: dict[str, dict[str, Any]] = {}
    for name, value in values.items():
        if name not in SETTINGS:
            raise SearchError(f"unknown parameter '{name}'; searchable: {', '.join(PARAM_NAMES)}")
        s = SETTINGS[name]
        v = int(math.ceil(value - 1e-9)) if s.integer else float(value)
        changes.setdefault(s.section, {})[name] = v
    out = dataclasses.replace(config, **{sec: dataclasses.replace(getattr(config, sec), **kv)
                                         for sec, kv in changes.items()})
    try:
        return out.validate("<searched values>")
    except ConfigError as err:
        raise SearchError(str(err)) from err
