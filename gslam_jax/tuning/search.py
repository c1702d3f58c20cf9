"""Batched parameter search: many parameter sets x many particles in one jitted computation.

The paper tuned alpha_d, alpha_theta_d, alpha_theta (eqs. 2-3) and the tempering constants
beta_prev, beta_new (eqs. 29-31) by hand per environment (section 7.3). Here a design of P points
over named ranges is evaluated with ``jax.vmap`` over parameter sets (the filter vmaps over
particles inside), the parameter axis sharded across every JAX device with a 1-D
``NamedSharding`` mesh, in equal chunks small enough to fit in memory (one compilation).

Objectives, computed inside JAX:

* ``"rms"``: RMS position error (m) after the least-squares 2-D rigid fit (paper 7.1) of the
  weighted-mean path (or the final best particle's path) onto the ground truth (Kabsch in 2-D).
* ``"loglik"``: the log marginal likelihood estimate, sum over updates of log sum_j w_j lambda_j
  (the log mean weight increment, ``StepInfo.log_lik``). Note: with tempering (beta != 1) this is
  not a normalised likelihood in the betas; compare it across alphas only.

Searchable: the filter's continuous parameters (``FILTER_PARAM_NAMES``: the alphas of eqs. 2-3,
the betas of eqs. 29-31) and the local-map observation settings of ``[map]``
(``OBS_PARAM_NAMES``: min_variance, obs_weight, min_points), applied inside the evaluated
function by ``cells.refine_obs`` to raw observations. Other config values are shapes or
discrete choices (static: a recompilation per value) or belong to the front-end (they change
the Run); they are not searched.

Common random numbers: every parameter set uses the same PRNG key (the only mode the batched
search supports), so differences in the objective reflect the parameters, not the draws.
"""

from __future__ import annotations

import csv
import json
import math
import tomllib
import warnings
from functools import partial
from pathlib import Path
from typing import Any, Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array, lax
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from scipy.stats import qmc

from gslam_jax import choices, rbpf, slam
from gslam_jax.rbpf import cells
from gslam_jax.config import Config, ConfigError
from gslam_jax.errors import InputError
from gslam_jax.machine import device_memory_limit, physical_memory
from gslam_jax.run import Run

__all__ = ["PARAM_NAMES", "FILTER_PARAM_NAMES", "OBS_PARAM_NAMES", "DESIGNS", "OBJECTIVES",
           "SearchError", "SearchSpace", "SearchResult", "ObsSettings", "parse_space",
           "load_space", "design_points", "unit_points", "params_from_values",
           "observations_from_values", "base_values", "obs_settings", "config_with_values",
           "search_inputs", "rigid_rms", "objective_value", "evaluate", "search", "auto_batch",
           "chunk_size", "default_inner", "rank", "design_values", "finish"]

FILTER_PARAM_NAMES = ("alpha_d", "alpha_theta_d", "alpha_theta", "beta_prev", "beta_new")
OBS_PARAM_NAMES = ("min_variance", "obs_weight", "min_points")  # [map], via cells.refine_obs
PARAM_NAMES = FILTER_PARAM_NAMES + OBS_PARAM_NAMES
_POSITIVE = ("beta_prev", "beta_new", "min_variance", "obs_weight")
DESIGNS = choices.SEARCH_DESIGNS
OBJECTIVES = choices.SEARCH_OBJECTIVES
PATHS = choices.SCORE_PATHS
PROGRESS_CHUNKS = 8  # chunks of a search whose sets run one after another (progress reports)


class SearchError(InputError):
    """A bad search space, design or objective; the message names the field."""


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


def _check_range(name: str, lo: Any, hi: Any, log: bool, source: str) -> tuple[float, float]:
    where = f"{source}: [space] {name}"
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
    if name == "min_points" and lo < 2:
        raise SearchError(f"{where}: range [{lo}, {hi}] must start at 2 or above (a cell "
                          f"needs two heights for a variance)")
    if lo < 0 or (name in _POSITIVE and lo <= 0):
        raise SearchError(f"{where}: range [{lo}, {hi}] must be "
                          f"{'positive' if name in _POSITIVE else 'non-negative'}")
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
        if name not in PARAM_NAMES:
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
        lo, hi = _check_range(name, spec[0], spec[1], log, source)
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


# ----------------------------------------------------------------------------- designs

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
        axis = np.linspace(0.0, 1.0, m) if m > 1 else np.array([0.5])
        unit = np.stack(np.meshgrid(*([axis] * d), indexing="ij"), -1).reshape(-1, d)
    else:
        unit = unit_points(design, n, d, seed)
    return space.scale(unit)


# ----------------------------------------------------------------------------- objectives


def params_from_values(values: Array, names: Sequence[str], base: rbpf.FilterParams
                       ) -> rbpf.FilterParams:
    """FilterParams whose named fields take the columns of ``values`` [..., d]; the others
    are broadcast from ``base``."""
    batch = values.shape[:-1]
    col = {n: values[..., i] for i, n in enumerate(names)}

    def pick(name: str, default) -> Array:
        if name in col:
            return col[name]
        return jnp.broadcast_to(jnp.asarray(default, values.dtype), batch)

    m = base.motion
    return rbpf.FilterParams(
        motion=m._replace(alpha_d=pick("alpha_d", m.alpha_d),
                          alpha_theta_d=pick("alpha_theta_d", m.alpha_theta_d),
                          alpha_theta=pick("alpha_theta", m.alpha_theta)),
        beta_prev=pick("beta_prev", base.beta_prev), beta_new=pick("beta_new", base.beta_new))


class ObsSettings(NamedTuple):
    """The ``[map]`` observation settings that the search applies on the device."""

    min_variance: Array | float = 1e-6
    obs_weight: Array | float = 1.0
    min_points: Array | float = 2.0


def obs_settings(config: Config) -> ObsSettings:
    m = config.map
    return ObsSettings(jnp.float32(m.min_variance), jnp.float32(m.obs_weight),
                       jnp.float32(m.min_points))


def observations_from_values(values: Array, names: Sequence[str], base: ObsSettings,
                             raw: Array) -> Array:
    """Local-map observations [M, L, L, 2] for one parameter row ``values`` [d]: the raw
    observations (``search_inputs``) refined by ``cells.refine_obs`` with the named
    ``OBS_PARAM_NAMES`` columns, the others from ``base``."""
    col = {n: values[i] for i, n in enumerate(names)}
    s = ObsSettings(*(col.get(f, getattr(base, f)) for f in ObsSettings._fields))
    return cells.refine_obs(raw, s.min_variance, s.obs_weight, s.min_points)


def refines_obs(names: Sequence[str]) -> bool:
    """True when ``names`` include an observation setting (raw observations needed)."""
    return any(n in OBS_PARAM_NAMES for n in names)


def search_inputs(run: Run, config: Config, names: Sequence[str]
                  ) -> tuple[slam.RunArrays, rbpf.FilterConfig]:
    """``slam.run_arrays``; when ``names`` include an observation setting, the local maps are
    raw observations (min_variance 0, weight 1, 2 points) that ``observations_from_values``
    refines on the device."""
    inputs, cfg = slam.run_arrays(run, config)
    if refines_obs(names):
        inputs = inputs._replace(local_obs=jnp.asarray(slam.local_observations(run, 0.0)))
    return inputs, cfg


def base_values(config: Config) -> dict[str, float]:
    """Every searchable parameter's value in ``config``."""
    m, f, mp = config.motion, config.filter, config.map
    return {"alpha_d": m.alpha_d, "alpha_theta_d": m.alpha_theta_d, "alpha_theta": m.alpha_theta,
            "beta_prev": f.beta_prev, "beta_new": f.beta_new, "min_variance": mp.min_variance,
            "obs_weight": mp.obs_weight, "min_points": float(mp.min_points)}


def config_with_values(config: Config, values: dict[str, float]) -> Config:
    """``config`` with searched/tuned values set (min_points: the threshold n >= ceil(value)
    that the search applied), checked by ``Config.validate``."""
    import dataclasses

    section = {"alpha_d": "motion", "alpha_theta_d": "motion", "alpha_theta": "motion",
               "beta_prev": "filter", "beta_new": "filter", "min_variance": "map",
               "obs_weight": "map", "min_points": "map"}
    changes: dict[str, dict[str, Any]] = {}
    for name, value in values.items():
        if name not in section:
            raise SearchError(f"unknown parameter '{name}'; searchable: {', '.join(PARAM_NAMES)}")
        v = int(math.ceil(value - 1e-9)) if name == "min_points" else float(value)
        changes.setdefault(section[name], {})[name] = v
    out = dataclasses.replace(config, **{sec: dataclasses.replace(getattr(config, sec), **kv)
                                         for sec, kv in changes.items()})
    try:
        return out.validate("<searched values>")
    except ConfigError as err:
        raise SearchError(str(err)) from err


def rigid_rms(estimate: Array, reference: Array, mask: Array) -> Array:
    """RMS distance after the least-squares 2-D rigid fit (Kabsch/Umeyama, no scale) of
    ``estimate`` [T, 2|3] onto ``reference`` over frames where ``mask`` [T] is true (paper 7.1;
    the JAX twin of ``metrics.rigid_fit_2d``). A mask with no true frame gives 0: callers
    (``evaluate``, ``search``) reject it first."""
    w = mask.astype(estimate.dtype)
    w = w / jnp.maximum(jnp.sum(w), 1.0)
    p, q = estimate[:, :2], reference[:, :2]
    mp, mq = w @ p, w @ q
    pc, qc = p - mp, q - mq
    dot = jnp.sum(w * (pc[:, 0] * qc[:, 0] + pc[:, 1] * qc[:, 1]))
    cross = jnp.sum(w * (pc[:, 0] * qc[:, 1] - pc[:, 1] * qc[:, 0]))
    ang = jnp.arctan2(cross, dot)
    c, s = jnp.cos(ang), jnp.sin(ang)
    rx = c * pc[:, 0] - s * pc[:, 1] - qc[:, 0]
    ry = s * pc[:, 0] + c * pc[:, 1] - qc[:, 1]
    return jnp.sqrt(jnp.sum(w * (rx * rx + ry * ry)))


def objective_value(out: rbpf.RunOutput, objective: str, reference: Array, mask: Array,
                    path: str = "mean") -> Array:
    """Scalar objective of one filter run (see the module docstring); NaN when the shared map
    store ran out of tiles (its maps, and so the run, are then not the filter's)."""
    if objective == "loglik":
        value = jnp.sum(out.infos.log_lik)
    else:
        est = {"mean": lambda: out.mean_pose, "best": lambda: out.best_path,
               "smoothed": lambda: rbpf.smoothed_mean_path(out.infos.pose, out.infos.ancestors,
                                                           out.final_state.log_w)}[path]()
        value = rigid_rms(est, reference, mask)
    return jnp.where(jnp.max(out.infos.map_status) > 0, jnp.nan, value)


_Inputs = slam.RunArrays


def _batch_fn(key: Array, inputs: _Inputs, base: rbpf.FilterParams, obs_base: ObsSettings,
              names: tuple[str, ...], cfg: rbpf.FilterConfig, objective: str, path: str,
              inner: int) -> Callable[[Array], Array]:
    """Objectives of a block of parameter sets [B, d] on one device: ``lax.map`` over the sets
    in vmapped groups of ``inner`` (inner = B: a plain vmap)."""

    def one(v: Array) -> Array:
        p = params_from_values(v, names, base)
        obs = (observations_from_values(v, names, obs_base, inputs.local_obs)
               if refines_obs(names) else inputs.local_obs)
        out = rbpf.run_filter(key, p, inputs.controls, inputs.obs_index, obs, cfg,
                            inputs.start)
        return objective_value(out, objective, inputs.reference, inputs.mask, path)

    def block(values: Array) -> Array:
        if inner == 1:  # never vmap, not even a block of one set: the conds would become selects
            return lax.map(one, values)
        if inner >= values.shape[0]:
            return jax.vmap(one)(values)
        return lax.map(one, values, batch_size=inner)

    return block


@partial(jax.jit, static_argnames=("names", "cfg", "objective", "path", "inner", "mesh"))
def _evaluate_batch(values: Array, key: Array, inputs: _Inputs, base: rbpf.FilterParams,
                    obs_base: ObsSettings, names: tuple[str, ...], cfg: rbpf.FilterConfig,
                    objective: str, path: str, inner: int, mesh: Mesh) -> Array:
    """shard_map over the 1-D device mesh: each device evaluates its block of sets."""
    spec, rep = PartitionSpec("p"), PartitionSpec()

    def per_device(values, key, inputs, base, obs_base):
        return _batch_fn(key, inputs, base, obs_base, names, cfg, objective, path,
                         inner)(values)

    return jax.shard_map(per_device, mesh=mesh, in_specs=(spec, rep, rep, rep, rep),
                         out_specs=spec, check_vma=False)(values, key, inputs, base, obs_base)


def evaluate(values: np.ndarray, key: Array, inputs: _Inputs, base: rbpf.FilterParams,
             names: tuple[str, ...], cfg: rbpf.FilterConfig, objective: str, path: str = "mean",
             batch: int | None = None, devices: Sequence[jax.Device] | None = None,
             progress: Callable[[int, int], None] | None = None, inner: int | None = None,
             obs_base: ObsSettings = ObsSettings()) -> np.ndarray:
    """Objective for every row of ``values`` [P, d]: balanced chunks of at most about ``batch``
    rows (``chunk_size``: a multiple of the device count; the last chunk padded), each sharded
    over a 1-D mesh on the parameter axis (``NamedSharding``, ``shard_map``). One compilation
    for all chunks.

    inner: sets vmapped together on one device. vmap turns the filter's data-dependent
    ``lax.cond`` (resample or not) into a select over every map, so on CPU the sets of a device
    run one after another in ``lax.map`` (inner=1, the default there); accelerators default to
    vmapping the whole per-device block (``default_inner``).

    obs_base: the observation settings not in ``names`` (``obs_settings(config)``); with an
    observation setting in ``names``, ``inputs.local_obs`` must be raw (``search_inputs``).

    Objective "rms" needs a frame with a ground-truth position (``inputs.mask``; headings are
    not used); a SearchError otherwise (``slam.require_ground_truth``).
    """
    if objective == "rms":
        slam.require_ground_truth(inputs.mask, "rms", SearchError)
    devices = list(devices or jax.devices())
    nd = len(devices)
    P = values.shape[0]
    batch = chunk_size(P, P if batch is None else batch, nd)
    mesh = Mesh(np.asarray(devices), ("p",))
    per_device = batch // nd
    inner = default_inner(devices) if inner is None else inner
    inner_ = per_device if inner is None else max(1, min(int(inner), per_device))
    sharded = NamedSharding(mesh, PartitionSpec("p"))
    replicated = NamedSharding(mesh, PartitionSpec())
    inputs = jax.device_put(inputs, replicated)
    base = jax.device_put(base, replicated)
    obs_base = jax.device_put(ObsSettings(*(jnp.float32(v) for v in obs_base)), replicated)
    key = jax.device_put(key, replicated)
    out = np.empty(P, np.float64)
    for start in range(0, P, batch):
        chunk = np.asarray(values[start:start + batch], np.float32)
        n = chunk.shape[0]
        if n < batch:  # pad with copies of the last row (discarded) to keep one shape
            chunk = np.concatenate([chunk, np.repeat(chunk[-1:], batch - n, axis=0)])
        vals = jax.device_put(chunk, sharded)
        res = _evaluate_batch(vals, key, inputs, base, obs_base, names, cfg, objective, path,
                              inner_, mesh)
        out[start:start + n] = np.asarray(jax.device_get(res), np.float64)[:n]
        if progress is not None:
            progress(start + n, P)
    return out


def default_inner(devices: Sequence[jax.Device]) -> int | None:
    """Sets vmapped together per device: 1 on CPU (``lax.map``, see ``evaluate``), None (the
    whole per-device block) on accelerators."""
    return 1 if devices[0].platform == "cpu" else None


def chunk_size(num_sets: int, max_batch: int, num_devices: int) -> int:
    """Sets per chunk: the fewest chunks of at most ``max_batch`` sets, balanced and rounded
    up to a multiple of the device count, so that the padding of the last chunk (which keeps
    one compiled shape) stays below one set per device and chunk. (Chunks of ``max_batch`` =
    47 for 64 sets would pad the second chunk to 47 and evaluate 94 sets.)"""
    chunks = math.ceil(num_sets / max(1, min(max_batch, num_sets)))
    return num_devices * math.ceil(num_sets / (chunks * num_devices))


def auto_batch(cfg: rbpf.FilterConfig, num_frames: int, budget_bytes: float | None = None,
               num_devices: int = 1, inner: int | None = None) -> int:
    """Largest number of parameter sets per chunk whose filter states fit in ``budget_bytes``
    (default: a quarter of each device's memory if the first reports it, else half of the
    host's physical memory, which CPU devices share).

    Per vmapped set: the maps (k, S) [J, H, W] float32, about 3 live copies during an update
    (old, updated, resampled under vmap), plus the per-frame poses/ancestors/weights [T, J].
    With ``inner`` sets vmapped per device in a ``lax.map`` (CPU: 1), only those are live at a
    time: memory does not bound the chunk (checked for the ``inner`` sets, then a bound far
    above any design is returned).
    """
    if budget_bytes is None:
        limit = device_memory_limit()
        # Accelerators report their own memory; CPU devices share the host's.
        budget_bytes = 0.25 * limit * num_devices if limit else 0.5 * physical_memory()
    J = cfg.num_particles
    H, W = cfg.map_shape
    per_set = 3 * 2 * 4 * J * H * W + num_frames * J * 4 * 6
    if inner is None:
        return max(1, int(budget_bytes // per_set))
    if num_devices * inner * per_set > budget_bytes:
        raise SearchError(f"{inner} vmapped parameter sets per device need "
                          f"{num_devices * inner * per_set / 2**20:.0f} MiB, over the budget of "
                          f"{budget_bytes / 2**20:.0f} MiB; lower inner or the particle count")
    return 2 ** 31 - 1


class SearchResult(NamedTuple):
    """Evaluated design, rows sorted best first (NaN rows last, flagged).

    total_seconds: wall time of every chunk, compilation included. first_chunk_seconds: the
    first chunk alone (compilation plus its compute), a part of ``total_seconds``, not to be
    added to it.
    """

    names: tuple[str, ...]
    values: np.ndarray     # [P, d] parameter values, best first
    objective: np.ndarray  # [P] objective values, best first (NaN last)
    objective_name: str
    maximize: bool
    total_seconds: float
    first_chunk_seconds: float

    @property
    def num_nan(self) -> int:
        return int(np.sum(~np.isfinite(self.objective)))

    def best(self) -> dict[str, float]:
        """The best parameter set; an error if every objective was NaN."""
        if not np.isfinite(self.objective[0]):
            raise SearchError(f"objective '{self.objective_name}' was NaN or infinite for all "
                              f"{len(self.objective)} parameter sets; nothing to rank")
        return dict(zip(self.names, map(float, self.values[0])))

    def rows(self) -> list[dict[str, Any]]:
        out = []
        for rank, (v, f) in enumerate(zip(self.values, self.objective), 1):
            ok = bool(np.isfinite(f))
            row = {"rank": rank if ok else None}
            row.update({n: float(x) for n, x in zip(self.names, v)})
            row[self.objective_name] = float(f) if ok else None
            row["status"] = "ok" if ok else "nan"
            out.append(row)
        return out

    def to_csv(self, path: str | Path) -> None:
        rows = self.rows()
        with open(path, "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
            writer.writeheader()
            for r in rows:
                writer.writerow({k: ("nan" if v is None and k == self.objective_name else
                                     ("" if v is None else v)) for k, v in r.items()})

    def to_json(self, path: str | Path) -> None:
        doc = {"objective": self.objective_name, "maximize": self.maximize,
               "total_seconds": self.total_seconds,
               "first_chunk_seconds": self.first_chunk_seconds,
               "num_nan": self.num_nan, "results": self.rows()}
        Path(path).write_text(json.dumps(doc, indent=2))


def rank(values: np.ndarray, objective: np.ndarray, maximize: bool
         ) -> tuple[np.ndarray, np.ndarray]:
    """Sort best first; NaN / infinite objectives go last whatever their sign."""
    f = np.asarray(objective, np.float64)
    finite = np.isfinite(f)
    key = np.where(finite, -f if maximize else f, 0.0)
    order = np.lexsort((key, ~finite))  # finite first, then by objective (stable)
    return values[order], f[order]


def design_values(run: Run, space: SearchSpace, design: str, n: int, objective: str,
                  path: str, seed: int, values: np.ndarray | None) -> np.ndarray:
    """Check a search request (objective, path, ground truth for "rms") and return its
    parameter values [P, d]: ``values`` if given, else the design's points."""
    if objective not in OBJECTIVES:
        raise SearchError(f"objective '{objective}' unknown; choose one of "
                          f"{', '.join(OBJECTIVES)}")
    if path not in PATHS:
        raise SearchError(f"path '{path}' unknown; choose one of {', '.join(PATHS)}")
    if objective == "rms" and run.ground_truth is None:
        raise SearchError("objective 'rms' needs the run's ground_truth, which is missing; "
                          "use objective 'loglik'")
    if values is None:
        values = design_points(space, design, n, seed)
    values = np.asarray(values, np.float64)
    if values.ndim != 2 or values.shape[1] != space.dim:
        raise SearchError(f"values must be [P, {space.dim}], got {values.shape}")
    return values


def search(run: Run, config: Config, space: SearchSpace, design: str = "halton", n: int = 64,
           objective: str = "rms", *, path: str = "mean", key: Array | None = None,
           crn: bool = True, seed: int = 0, batch: int | None = None,
           devices: Sequence[jax.Device] | None = None,
           progress: Callable[[int, int], None] | None = None,
           values: np.ndarray | None = None, inner: int | None = None) -> SearchResult:
    """Evaluate ``n`` parameter sets of ``design`` over ``space`` on ``run``; best first.

    config: everything not searched (particles, resampler, map, and the base values of the
    parameters not in ``space``). objective: "rms" (needs ground truth; m, lower is better) or
    "loglik" (higher is better). path: "mean" (weighted-mean pose per frame), "best" (the
    final best particle's path) or "smoothed" (``rbpf.smoothed_mean_path``) for "rms". crn:
    the same PRNG key for every set (common random numbers); only True is supported (False is
    a SearchError: repeat the search with other keys instead). batch: sets per chunk (default
    ``auto_batch``). values: an explicit [P, d] design (overrides design and n). inner: sets
    vmapped together per device (see ``evaluate``). The result's ``total_seconds`` include
    compilation; ``first_chunk_seconds`` are the part spent on the first chunk (compilation
    and its compute).
    """
    import time

    values = design_values(run, space, design, n, objective, path, seed, values)
    inputs, cfg = search_inputs(run, config, space.names)  # evaluate() checks "rms"'s truth
    base = slam.filter_params(config)
    key = jax.random.key(config.filter.seed) if key is None else key
    if not crn:
        raise SearchError("crn=False is not supported by the batched search: every set uses "
                          "the same key (common random numbers); repeat the search with "
                          "different keys instead")
    devices = list(devices or jax.devices())
    inner = default_inner(devices) if inner is None else inner
    if batch is None:
        batch = auto_batch(cfg, run.num_frames, num_devices=len(devices), inner=inner)
        if inner is not None:  # sets run one after another: chunks for progress reports
            batch = min(batch, math.ceil(len(values) / PROGRESS_CHUNKS))
    t0 = time.perf_counter()
    first_chunk_s = 0.0
    first = [True]

    def timed_progress(done: int, total: int) -> None:
        nonlocal first_chunk_s
        if first[0]:
            first_chunk_s = time.perf_counter() - t0  # compilation and the first chunk
            first[0] = False
        if progress is not None:
            progress(done, total)

    f = evaluate(values, key, inputs, base, tuple(space.names), cfg, objective, path,
                 batch=batch, devices=devices, progress=timed_progress, inner=inner,
                 obs_base=obs_settings(config))
    return finish(space, values, f, objective, time.perf_counter() - t0, first_chunk_s)


POOL_NOTE = ('with [map] store = "shared", a run whose tile pool ran out scores NaN too: raise '
             '[map] pool_tiles')


def finish(space: SearchSpace, values: np.ndarray, f: np.ndarray, objective: str,
           total_s: float, first_chunk_s: float) -> SearchResult:
    """Rank evaluated sets into a SearchResult: a SearchError when every objective is NaN, a
    RuntimeWarning naming one when some are (shared by ``search`` and
    ``distributed.distributed_search``)."""
    bad = ~np.isfinite(f)
    if bad.all():
        raise SearchError(f"objective '{objective}' is NaN or infinite for every one of the "
                          f"{len(f)} parameter sets (first: "
                          f"{dict(zip(space.names, values[0].round(6)))}); check the run and "
                          f"the ranges ({POOL_NOTE})")
    if bad.any():
        first_bad = dict(zip(space.names, values[np.argmax(bad)].round(6)))
        warnings.warn(f"objective '{objective}' is NaN for {int(bad.sum())} of {len(f)} "
                      f"parameter sets (e.g. {first_bad}); they are reported last, never "
                      f"ranked best ({POOL_NOTE})", RuntimeWarning)
    maximize = objective == "loglik"
    vals, obj = rank(values, f, maximize)
    return SearchResult(tuple(space.names), vals, obj, objective, maximize, total_s,
                        first_chunk_s)
