"""Whose map a particle is scored on after a loop's revisit: the start's, or the one it wrote
itself on the way in. Asks why a hypothesis near the truth can lose the weights to ones metres
off (docs/notebook/results.md, "A real vehicle's 799 m loop").

    python -m experiments.revisit_terms --course arroyo-a --config configs/table1.toml \\
        --kitti ../shared/data/kitti-poses/00.txt --length 800 --seed 2 \\
        --set filter.unknown_cells=sample --set map.store=shared

Runs the filter over the loop (as ``loop_cloud``, in chunks of ``--chunk`` frames). At the
chunk before the approach frame (``loop_closure.approach_frame``) it keeps a copy of every
particle's map and from then on follows each particle's lineage through the resamplings. At
the end of every later chunk, up to ``--after`` metres past the revisit, the particles are
moved to the next update's frame by the motion model's mean, and that update's local map is
scored against their maps (eq. 26, ``importance.known_cell_terms``). Its known cells are split
into "old" ones, which the particle's ancestor already knew at the approach, and "new" ones,
first written since (the particle's own local maps on the way in). Per row, over the particles
within ``NEAR_M`` of the truth ("near") and those over ``FAR_M`` from it ("far"), medians of:
heading error; the old cells' share of the known ones; eq. 26 per known cell on old, new and
all known cells; and per known cell at the true pose against the same particles' maps, and at
their own position with the true heading.
"""

from __future__ import annotations

import argparse
import json
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from experiments.loop_closure import approach_frame
from experiments.loop_cloud import NEAR_M, add_loop_arguments, simulated_loop
from experiments.loop_paths import START_M
from gslam_jax import rbpf
from gslam_jax.driver import slam
from gslam_jax.driver.observations import map_observations
from gslam_jax.driver.results import ChunkReport
from gslam_jax.driver.sizing import filter_params
from gslam_jax.evaluation import loops
from gslam_jax.gridmap.grid import arc_length
from gslam_jax.rbpf import maps
from gslam_jax.rbpf.footprint import compact_observation, read_footprints
from gslam_jax.rbpf.importance import cell_noise, known_cell_terms
from gslam_jax.rbpf.motion import apply_motion
from gslam_jax.vo.localmap import localmap_params

FAR_M = 5.0  # m: particles this far from the truth are the "far" group


def carry_lineage(lineage: np.ndarray, ancestors: np.ndarray) -> np.ndarray:
    """Each slot's ancestor slot at the snapshot, ``lineage`` [J], carried through frames whose
    ``ancestors`` [n, J] (``StepInfo.ancestors``: slot j's parent before that frame) follow."""
    for parents in ancestors:
        lineage = lineage[parents]
    return lineage


def split_terms(known: np.ndarray, known_before: np.ndarray, lam: np.ndarray
                ) -> dict[str, np.ndarray]:
    """Per particle (rows of the [J, M] arrays): the share of its ``known`` cells that were
    ``known_before`` ("old"), and the mean eq. 26 term ``lam`` per known cell on the old, the
    new and all known cells (NaN where a particle has none of that kind)."""
    old, new = known & known_before, known & ~known_before

    def mean(mask: np.ndarray) -> np.ndarray:
        n = mask.sum(axis=1)
        return np.where(n > 0, np.where(mask, lam, 0.0).sum(axis=1) / np.maximum(n, 1), np.nan)

    n_known = known.sum(axis=1)
    return {"old_share": np.where(n_known > 0, old.sum(axis=1) / np.maximum(n_known, 1), np.nan),
            "per_cell_old": mean(old), "per_cell_new": mean(new), "per_cell": mean(known)}


def group_medians(values: dict[str, np.ndarray], groups: dict[str, np.ndarray]
                  ) -> dict[str, float]:
    """``{name}_{group}``: the median of each value over each group's particles (NaN for an
    empty group or where none has the value)."""
    out = {}
    for name, v in values.items():
        for g, mask in groups.items():
            x = v[mask]
            x = x[np.isfinite(x)]
            out[f"{name}_{g}"] = float(np.median(x)) if x.size else float("nan")
    return out


@partial(jax.jit, static_argnames=("cfg",))
def _known_cell_terms(store: maps.Maps, cfg: rbpf.FilterConfig, pose: jax.Array,
                      rows: jax.Array, local_obs: jax.Array, lattice_heading: jax.Array,
                      key: jax.Array, params: rbpf.FilterParams) -> tuple[jax.Array, jax.Array]:
    """(known [J, M], eq. 26 per observed cell [J, M]): ``local_obs`` scored from ``pose``
    [J, 3] against the ``rows`` [J] of ``store``, one compiled program per ``cfg``."""
    obs = compact_observation(local_obs, cfg, lattice_heading)
    u = jax.random.uniform(key, (cfg.num_particles, cfg.unknown_samples))
    fp = read_footprints(store, pose, rows, u, obs, cfg)
    return known_cell_terms(fp.k_obs, fp.S_obs, fp.k_prior, fp.S_prior,
                            cell_noise(obs.index, params))


class _Scorer:
    """Scores one update's local map for every particle against the given maps."""

    def __init__(self, report: ChunkReport, config):
        self.params = filter_params(config, report.run)
        self.observations = map_observations(report.run, config)
        self.rows = np.arange(report.cfg.num_particles)

    def __call__(self, store: maps.Maps, cfg: rbpf.FilterConfig, pose: np.ndarray,
                 rows: np.ndarray, local_obs, lattice_heading: float, frame: int
                 ) -> tuple[np.ndarray, np.ndarray]:
        """(known [J, M], eq. 26 per observed cell [J, M]) at ``pose`` [J, 3] against the
        ``rows`` of ``store`` (``cfg``: the one the store was made with; a shared pool may
        have grown since the snapshot)."""
        known, lam = _known_cell_terms(store, cfg, jnp.asarray(pose, jnp.float32),
                                       jnp.asarray(rows, jnp.int32), jnp.asarray(local_obs),
                                       jnp.float32(lattice_heading), jax.random.key(frame),
                                       self.params)
        return np.asarray(known), np.asarray(lam)


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_loop_arguments(ap)
    ap.add_argument("--after", type=float, default=25.0,
                    help="metres of travel past the revisit to follow")
    ap.add_argument("--chunk", type=int, default=16, help="frames per row")
    ap.add_argument("--json", type=Path, help="write the rows here")
    args = ap.parse_args(argv)
    loop, run, config = simulated_loop(args)
    truth = np.asarray(run.ground_truth, np.float64)
    revisit = loops.find_revisit(truth, START_M, 0.5 * loop.length_m)
    if revisit is None:
        raise SystemExit(f"{loop.name}: the path does not come back within {START_M} m")
    arc = arc_length(truth)
    first = approach_frame(truth, revisit, localmap_params(config).max_range) - args.chunk
    last = int(np.searchsorted(arc, arc[revisit.j] + args.after))
    print(f"{loop.name}: revisit at frames {revisit.i} and {revisit.j}, {arc[revisit.j]:.1f} m; "
          f"rows from frame {first} to {last}")
    rows: list[dict] = []
    state: dict = {}

    def on_chunk(r: ChunkReport) -> None:
        end = r.start + len(r.best_pose) - 1
        if "lineage" in state:
            state["lineage"] = carry_lineage(state["lineage"], np.asarray(r.info.ancestors))
        if end < first or end >= last:
            return
        if "snapshot" not in state:  # a copy: the chunk's state is donated to the next chunk
            state["snapshot"] = jax.tree.map(jnp.copy, r.state.maps), r.cfg
            state["lineage"] = np.arange(r.cfg.num_particles)
            state["score"] = _Scorer(r, config)
            return
        index = np.asarray(r.run.obs_index)
        ahead = np.flatnonzero(index[end + 1:end + 1 + args.chunk] >= 0)
        if ahead.size == 0:
            return
        frame = end + 1 + int(ahead[0])
        score = state["score"]
        motion = score.params.motion
        pose = r.state.pose
        for t in range(end + 1, frame + 1):
            pose = apply_motion(pose, jnp.asarray(r.run.controls[t], jnp.float32)[None],
                                jnp.zeros(pose.shape, pose.dtype), motion)
        pose = np.asarray(pose)
        local = score.observations[int(index[frame])]
        heading = float(r.run.lattice_heading_array()[int(index[frame])])
        at = (local, heading, frame)
        known, lam = score(r.state.maps, r.cfg, pose, score.rows, *at)
        known_before, _ = score(*state["snapshot"], pose, state["lineage"], *at)
        true_pose = np.asarray(r.run.ground_truth, np.float64)[frame]
        own_heading = pose.copy()
        own_heading[:, 2] = true_pose[2]
        values = split_terms(known, known_before, lam)
        values["per_cell_at_truth"] = _per_cell(*score(
            r.state.maps, r.cfg, np.broadcast_to(true_pose, pose.shape), score.rows, *at))
        values["per_cell_true_heading"] = _per_cell(*score(r.state.maps, r.cfg, own_heading,
                                                           score.rows, *at))
        dist = np.hypot(*(pose[:, :2] - true_pose[:2]).T)
        values["heading_err_deg"] = np.degrees(np.angle(np.exp(1j * (pose[:, 2]
                                                                     - true_pose[2]))))
        near, far = dist <= NEAR_M, dist > FAR_M
        w = np.exp(np.asarray(r.state.log_w))
        row = {"frame": frame, "travel_m": float(arc[frame]), "near": int(near.sum()),
               "far": int(far.sum()), "weight_near": float(w[near].sum()),
               "nearest_m": float(dist.min()),
               **group_medians(values, {"near": near, "far": far})}
        rows.append(row)
        _print(row)

    res = slam.run_slam(run, config, chunk=args.chunk, on_chunk=on_chunk)
    error = loops.revisit_error(truth, res.best_path, revisit.i, revisit.j)
    print(f"revisit error of the best path: {error:.2f} m")
    if args.json:
        args.json.write_text(json.dumps({"loop": loop.name, "seed": args.seed,
                                         "revisit_error_m": error, "rows": rows}, indent=1))
    return rows


def _per_cell(known: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """Mean eq. 26 term per known cell of each particle [J] (NaN where none is known)."""
    return split_terms(known, known, lam)["per_cell"]


def _print(row: dict) -> None:
    def f(key: str) -> str:
        return f"{row[key + '_near']:5.2f} {row[key + '_far']:5.2f}"

    print(f"{row['travel_m']:6.1f} m | near {row['near']:3d} ({row['weight_near']:.3f}) far "
          f"{row['far']:3d} | heading err deg {f('heading_err_deg')} | old share "
          f"{f('old_share')} | per cell: old {f('per_cell_old')} new {f('per_cell_new')} all "
          f"{f('per_cell')} | at the truth {f('per_cell_at_truth')} | true heading "
          f"{f('per_cell_true_heading')}", flush=True)


if __name__ == "__main__":
    main()
