"""Batched evaluation: the objective of many parameter sets x many particles in one jitted
computation.

A chunk of P parameter sets is evaluated with ``jax.vmap`` / ``lax.map`` over the sets (the
filter vmaps over particles inside), the set axis sharded across every JAX device with a 1-D
``NamedSharding`` mesh, in equal chunks small enough to fit in memory (one compilation).

Objectives, computed inside JAX:

* ``"rms"``: RMS position error (m) after the least-squares 2-D rigid fit (paper 7.1) of the
  weighted-mean path (or the final best particle's, or the smoothed path) onto the ground
  truth (Kabsch in 2-D).
* ``"loglik"``: the log marginal likelihood estimate, sum over updates of log sum_j w_j lambda_j
  (the log mean weight increment, ``StepInfo.log_lik``). Note: with tempering (beta != 1) this is
  not a normalised likelihood in the betas; compare it across alphas only, and with adaptive
  tempering not even that (the exponent changes with the alphas; ``evidence_fit`` fixes it).
  NaN when a particle observed cells beyond the map's edge.

Every set uses the same PRNG key (common random numbers), so differences in the objective
reflect the parameters, not the draws.
"""

from __future__ import annotations

import math
from functools import partial
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array, lax
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from gslam_jax import choices, rbpf
from gslam_jax.driver import device_arrays, observations
from gslam_jax.driver.machine import device_memory_limit, physical_memory
from gslam_jax.tuning.space import (
    OBS_PARAM_NAMES,
    SearchError,
    observations_from_values,
    params_from_values,
)

__all__ = ["OBJECTIVES", "PATHS", "rigid_rms", "objective_value", "evaluate", "default_inner",
           "chunk_size", "auto_batch"]

OBJECTIVES = choices.SEARCH_OBJECTIVES
PATHS = choices.SCORE_PATHS


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
                    path: str = "mean", footprints: Array | None = None) -> Array:
    """Scalar objective of one filter run (see the module docstring); NaN when the shared map
    store ran out of tiles (its maps, and so the run, are then not the filter's), and for
    "loglik" when a particle observed cells beyond the map's edge (they are neither weighed
    nor mapped, so the evidence is not the whole log's: a noise wide enough to carry the
    particles off the map would otherwise score by what it skips). ``footprints``: the run's
    local map footprints [T, 3] (``RunArrays.footprints``), which the "local_steps" path
    needs."""
    if objective == "loglik":
        value = jnp.sum(out.infos.log_lik)
        value = jnp.where(jnp.sum(out.infos.extent_violations) > 0, jnp.nan, value)
    else:
        est = {"mean": lambda: out.mean_pose, "best": lambda: out.best_path}.get(
            path, lambda: rbpf.ancestry_path(
                path, out.infos.pose, out.infos.ancestors, out.final_state.log_w,
                out.final_state.best,
                None if footprints is None else
                rbpf.step_history(out.infos.log_w, out.infos.resampled, out.mean_pose,
                                  footprints)))()
        value = rigid_rms(est, reference, mask)
    return jnp.where(jnp.max(out.infos.map_status) > 0, jnp.nan, value)


_Inputs = device_arrays.RunArrays


def _batch_fn(key: Array, inputs: _Inputs, base: rbpf.FilterParams, names: tuple[str, ...],
              cfg: rbpf.FilterConfig, objective: str, path: str, inner: int
              ) -> Callable[[Array], Array]:
    """Objectives of a block of parameter sets [B, d] on one device: ``lax.map`` over the sets
    in vmapped groups of ``inner`` (inner = B: a plain vmap). The raw observations are refined
    per set when ``names`` hold an observation setting, else once for the block."""
    per_set = any(n in OBS_PARAM_NAMES for n in names)

    def one(v: Array, shared: Array | None) -> Array:
        p = params_from_values(v, names, base)
        obs = (observations_from_values(v, names, inputs.obs, inputs.local_obs)
               if shared is None else shared)
        out = rbpf.run_filter(key, p, inputs.controls, inputs.obs_index, obs, cfg,
                              inputs.start, inputs.lattice_headings, inputs.fallback)
        return objective_value(out, objective, inputs.reference, inputs.mask, path,
                               inputs.footprints)

    def block(values: Array) -> Array:
        shared = None if per_set else observations.refine_observations(inputs.local_obs, inputs.obs)
        one_ = partial(one, shared=shared)
        if inner == 1:  # never vmap, not even a block of one set: the conds would become selects
            return lax.map(one_, values)
        if inner >= values.shape[0]:
            return jax.vmap(one_)(values)
        return lax.map(one_, values, batch_size=inner)

    return block


@partial(jax.jit, static_argnames=("names", "cfg", "objective", "path", "inner", "mesh"))
def _evaluate_batch(values: Array, key: Array, inputs: _Inputs, base: rbpf.FilterParams,
                    names: tuple[str, ...], cfg: rbpf.FilterConfig, objective: str, path: str,
                    inner: int, mesh: Mesh) -> Array:
    """shard_map over the 1-D device mesh: each device evaluates its block of sets."""
    spec, rep = PartitionSpec("p"), PartitionSpec()

    def per_device(values, key, inputs, base):
        return _batch_fn(key, inputs, base, names, cfg, objective, path, inner)(values)

    return jax.shard_map(per_device, mesh=mesh, in_specs=(spec, rep, rep, rep),
                         out_specs=spec, check_vma=False)(values, key, inputs, base)


def evaluate(values: np.ndarray, key: Array, inputs: _Inputs, base: rbpf.FilterParams,
             names: tuple[str, ...], cfg: rbpf.FilterConfig, objective: str, path: str = "mean",
             batch: int | None = None, devices: Sequence[jax.Device] | None = None,
             progress: Callable[[int, int], None] | None = None, inner: int | None = None
             ) -> np.ndarray:
    """Objective for every row of ``values`` [P, d]: balanced chunks of at most about ``batch``
    rows (``chunk_size``: a multiple of the device count; the last chunk padded), each sharded
    over a 1-D mesh on the parameter axis (``NamedSharding``, ``shard_map``). One compilation
    for all chunks.

    inner: sets vmapped together on one device. vmap turns the filter's data-dependent
    ``lax.cond`` (resample or not) into a select over every map, so on CPU the sets of a device
    run one after another in ``lax.map`` (inner=1, the default there); accelerators default to
    vmapping the whole per-device block (``default_inner``).

    inputs: ``device_arrays.run_arrays``; the observation settings not in ``names`` are
    ``inputs.obs``.

    Objective "rms" needs a frame with a ground-truth position (``inputs.mask``; headings are
    not used); a SearchError otherwise (``device_arrays.require_ground_truth``).
    """
    if objective == "rms":
        device_arrays.require_ground_truth(inputs.mask, "rms", SearchError)
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
    key = jax.device_put(key, replicated)
    out = np.empty(P, np.float64)
    for start in range(0, P, batch):
        chunk = np.asarray(values[start:start + batch], np.float32)
        n = chunk.shape[0]
        if n < batch:  # pad with copies of the last row (discarded) to keep one shape
            chunk = np.concatenate([chunk, np.repeat(chunk[-1:], batch - n, axis=0)])
        vals = jax.device_put(chunk, sharded)
        res = _evaluate_batch(vals, key, inputs, base, names, cfg, objective, path, inner_,
                              mesh)
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


