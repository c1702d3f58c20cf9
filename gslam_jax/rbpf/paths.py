"""Trajectory estimates from the particles' per-frame poses and resampling ancestry: each
frame's weighted mean pose, the best particle's path through its ancestry (the paper's
estimate), the path of the final cloud's densest particle, the particle smoother's mean path
over every final particle or over the densest particle's neighbourhood alone, and the path of
its mean steps, weighed by the final weights or each by the factors that bear on it; and which
particle's map goes with an estimate."""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array, lax

from gslam_jax.rbpf.motion import control_between, world_step

__all__ = ["weighted_mean_pose", "backtrack_path", "densest_particle", "MODE_RADIUS_M",
           "mode_weights", "smoothed_mean_path", "mode_mean_path", "smoothed_step_path",
           "compose_steps", "StepHistory", "step_history", "COVER_SPREADS", "factor_cover",
           "local_step_path", "ancestry_path", "map_particle"]

# The neighbourhood ``densest_particle`` sums the weight over: a loop closure's tolerance
# (``loops.TOLERANCE``), so the mode is where most of the weight agrees to that precision.
MODE_RADIUS_M = 1.0


def weighted_mean_pose(w: Array, pose: Array) -> Array:
    """Mean of poses [J, 3] under normalised weights w [J] (circular mean for the heading)."""
    xy = w @ pose[:, :2]
    th = jnp.arctan2(w @ jnp.sin(pose[:, 2]), w @ jnp.cos(pose[:, 2]))
    return jnp.concatenate([xy, th[None]])


def backtrack_path(poses: Array, ancestors: Array, last: Array) -> Array:
    """Follow ancestry back from particle ``last`` at the final frame: [T, J, 3] -> [T, 3]."""

    def back(j, xs):
        pose_t, anc_t = xs
        return anc_t[j], pose_t[j]

    _, path = lax.scan(back, last, (poses, ancestors), reverse=True)
    return path


@partial(jax.jit, static_argnames="radius")
def densest_particle(pose: Array, log_w: Array, radius: float = MODE_RADIUS_M) -> Array:
    """The slot [] of the particle whose neighbourhood (positions within ``radius`` metres of
    its own, itself included) holds the most weight, ties to its own higher weight: the
    posterior's mode as the cloud [J, 3] with log weights [J] shows it. After a resampling the
    weights are nearly equal and the highest-weight particle is close to a random pick, which
    after a loop's revisit can be one of the few that missed the start's map while most of the
    weight sits near the truth. The J^2 distances are summed a block of rows at a time."""
    w = jnp.exp(log_w - jax.nn.logsumexp(log_w))
    xy = pose[:, :2]

    def mass(p: Array) -> Array:
        near = jnp.sum((xy - p) ** 2, axis=-1) <= radius * radius
        return jnp.sum(jnp.where(near, w, 0.0))

    m = lax.map(mass, xy, batch_size=256)
    return jnp.argmax(jnp.where(m >= jnp.max(m), w, -1.0)).astype(jnp.int32)


def mode_weights(pose: Array, log_w: Array, densest: Array) -> Array:
    """The log weights [J] restricted to the mode's component: ``log_w`` where a particle of
    the cloud [J, 3] lies within ``MODE_RADIUS_M`` of particle ``densest`` (the
    ``densest_particle``), -inf elsewhere (not normalised)."""
    centre = pose[densest, :2]
    near = jnp.sum((pose[:, :2] - centre) ** 2, axis=-1) <= MODE_RADIUS_M * MODE_RADIUS_M
    return jnp.where(near, log_w, -jnp.inf)


@jax.jit
def smoothed_mean_path(poses: Array, ancestors: Array, log_w: Array) -> Array:
    """The particle smoother's posterior mean trajectory (Kitagawa 1996; Doucet and Johansen
    2011, sec. 4.3): every final particle's path through its ancestry, averaged with the final
    normalised weights ``log_w`` [J] (heading by circular mean): [T, J, 3] -> [T, 3].

    Walks back once, carrying each slot's share of the final weight (a parent's share is the
    sum of its children's), so the J paths are never materialised: O(J) memory besides the
    inputs. Frames where all surviving paths share one ancestor give that ancestor's pose, as
    the best path does; where many lineages survive it averages them."""
    J = log_w.shape[0]

    def back(w, xs):
        pose_t, anc_t = xs
        return jax.ops.segment_sum(w, anc_t, num_segments=J), weighted_mean_pose(w, pose_t)

    _, path = lax.scan(back, jnp.exp(log_w - jax.nn.logsumexp(log_w)), (poses, ancestors),
                       reverse=True)
    return path


@jax.jit
def mode_mean_path(poses: Array, ancestors: Array, log_w: Array,
                   densest: Array | None = None) -> Array:
    """The particle smoother's mean path over the mode's component alone: the final
    particles within ``MODE_RADIUS_M`` of the ``densest_particle``, their ancestral paths
    averaged with their final weights renormalised (``smoothed_mean_path`` under
    ``mode_weights``): [T, J, 3] -> [T, 3]. The posterior mean given the dominant mode, as
    AMCL reports the mean of its heaviest cluster. After a loop's revisit the posterior is
    split between particles that met the start's map and a few that missed it: the mean over
    all of them lies between the two, the densest particle's path is one sample of its
    component, and this is that component's mean. ``densest``: that particle's slot where
    the caller has it already."""
    if densest is None:
        densest = densest_particle(poses[-1], log_w)
    return smoothed_mean_path(poses, ancestors, mode_weights(poses[-1], log_w, densest))


@jax.jit
def smoothed_step_path(poses: Array, ancestors: Array, log_w: Array) -> Array:
    """The path of the particle smoother's mean steps: at each frame the final weights' mean
    of the step every final particle's ancestral path takes there (in the frame of the step's
    start), composed from their mean start: [T, J, 3] -> [T, 3].

    ``smoothed_mean_path`` averages positions. Where the particles' headings spread and the
    weights are nearly flat (stereo's ESS target), their positions lie inside the arc the
    headings span, so that mean path is shorter than each particle's by about the mean of
    1 - cos of the spread, a scale error the rigid fit behind the RMS cannot remove
    (docs/notebook/real-data.md, "What the gain over VO is made of"). Mean steps do not
    shorten: their lengths are the particles' mean step lengths. The heading is the sum of mean turns (not
    wrapped). One backward pass as ``smoothed_mean_path`` (the weight shares of each frame's
    slots), then a forward composition."""
    J = log_w.shape[0]

    def back(w, xs):
        pose_t, anc_t, prev = xs
        shares = jax.ops.segment_sum(w, anc_t, num_segments=J)
        return shares, w @ control_between(prev[anc_t], pose_t)

    w_final = jnp.exp(log_w - jax.nn.logsumexp(log_w))
    w_first, steps = lax.scan(back, w_final, (poses[1:], ancestors[1:], poses[:-1]),
                              reverse=True)
    return compose_steps(weighted_mean_pose(w_first, poses[0]), steps)


def compose_steps(start: Array, steps: Array) -> Array:
    """The path [T, 3] that leaves ``start`` [3] by ``steps`` [T - 1, 3] (each in the frame of
    its own start, as ``control_between`` gives them; eq. 1 without noise). The heading is the
    sum of the turns (not wrapped)."""

    def forward(pose, step):
        nxt = pose + jnp.stack([*world_step(pose, step), step[2]])
        return nxt, nxt

    _, path = lax.scan(forward, start, steps)
    return jnp.concatenate([start[None], path], axis=0)


class StepHistory(NamedTuple):
    """What ``local_step_path`` needs beside the poses and ancestry, per frame."""

    log_w: Array      # [T, J] normalised log weights after each frame (``StepInfo.log_w``)
    resampled: Array  # [T] bool
    mean_pose: Array  # [T, 3] each frame's weighted mean pose, where its local map is placed
    footprint: Array  # [T, 3] the frame's local map's observed cells: their centre x, y in the
    #                   robot frame and the radius about it that holds them (m); radius < 0
    #                   where the frame has no local map (``observations.local_map_footprints``)


def step_history(log_w, resampled, mean_pose, footprint) -> StepHistory:
    """A run's ``StepHistory`` (device arrays; poses and footprints float32) from its per-frame
    log weights [T, J] and resampling flags [T] (``StepInfo``), weighted mean poses [T, 3] and
    local map footprints [T, 3], host or device arrays."""
    return StepHistory(jnp.asarray(log_w), jnp.asarray(resampled),
                       jnp.asarray(mean_pose, jnp.float32), jnp.asarray(footprint, jnp.float32))


# How far two frames' local maps may lie from where the mean path places them, in the
# position spread the cloud gained between the two: ``factor_cover`` widens their overlap by
# it, so that a revisit the particles make while their mean path misses it still counts (a
# wider cover only adds factors to a step), while neighbouring frames, whose relative poses
# the cloud hardly spreads, keep their own footprints.
COVER_SPREADS = 3.0


@jax.jit
def factor_cover(poses: Array, history: StepHistory) -> Array:
    """The first step [T] each frame's importance factor bears on: one after the oldest frame
    whose local map its own overlaps (``history.footprint`` placed at the mean poses, the
    overlap widened by ``COVER_SPREADS`` times the position spread the cloud gained between
    the two frames, sqrt(|s_u^2 - s_s^2|) of its spreads s about the mean); u + 1 (none) for a
    frame u without a local map or one that overlaps no older one. An update scores its local
    map against the cells the older overlapping maps wrote, so its factor depends on the steps
    from there to itself and on no other (eq. 30; eq. 31 also on the map's known cells, which
    this ignores). At a loop's revisit that is the whole loop."""
    T = poses.shape[0]
    centre = history.mean_pose[:, :2] + jnp.stack(
        world_step(history.mean_pose, history.footprint), axis=-1)
    w = jax.nn.softmax(history.log_w, axis=-1)
    spread = jnp.sqrt(jnp.sum(w * jnp.sum((poses[..., :2] - history.mean_pose[:, None, :2]) ** 2,
                                          axis=-1), axis=-1))
    has = history.footprint[:, 2] >= 0
    radius = history.footprint[:, 2]
    frames = jnp.arange(T)

    def first(u: Array) -> Array:
        d2 = jnp.sum((centre - centre[u]) ** 2, axis=-1)
        gained = jnp.sqrt(jnp.abs(spread[u] ** 2 - spread ** 2))
        reach = radius + radius[u] + COVER_SPREADS * gained
        near = has & has[u] & (frames < u) & (d2 <= reach ** 2)
        return jnp.min(jnp.where(near, frames, u)) + 1

    return lax.map(first, frames, batch_size=256)


@jax.jit
def local_step_path(poses: Array, ancestors: Array, history: StepHistory,
                    first: Array) -> Array:
    """The path of mean steps, each weighed by the importance factors that bear on it alone:
    at frame t the mean, over the final particles' ancestral paths, of their steps into t,
    weighed by the factors of the frames u with ``first[u]`` <= t <= u (``factor_cover``),
    composed from their start: [T, J, 3] -> [T, 3].

    ``smoothed_step_path`` weighs every step by the final weights, the product of all the
    factors. To first order in the factors (stereo's tempered, nearly flat weights) a step's
    posterior mean moves only by the factors that depend on it; the others (made before it,
    or by updates whose maps do not reach back to it) only add Monte Carlo error
    (docs/notebook/real-data.md, "Where the seeds' spread comes from"). The factors before the last
    resampling are already in which lineages survived it, and are not weighed again; with
    one factor after it that covers every step this is ``smoothed_step_path``. The start:
    the lineages' mean at frame 0 under the first step's weights. One backward pass, which
    carries each lineage's slot and the sum of the factors covering the step (those a step
    leaves behind are dropped by the first step they cover): O(J) memory besides the
    inputs."""
    T, J = history.log_w.shape
    frames = jnp.arange(T)
    last = jnp.max(jnp.where(history.resampled, frames, 0))
    change = jnp.diff(history.log_w, axis=0, prepend=history.log_w[:1])
    covers = (frames > last) & (first <= frames)  # after it slot j is final particle j
    factors = jnp.where(covers[:, None], change, 0.0)
    # the factors by the first step they cover: leaving that step (backwards) drops them
    ends = jax.ops.segment_sum(factors, first, num_segments=T + 1)

    def back(carry, xs):
        slots, log_w = carry
        pose_t, anc_t, prev, factor_t, end_next = xs
        log_w = log_w + factor_t - end_next          # the factors that cover step t
        parents = anc_t[slots]
        step = jax.nn.softmax(log_w) @ control_between(prev[parents], pose_t[slots])
        return (parents, log_w), step

    (slots0, log_w1), steps = lax.scan(
        back, (jnp.arange(J), jnp.zeros(J)),
        (poses[1:], ancestors[1:], poses[:-1], factors[1:], ends[2:]), reverse=True)
    return compose_steps(weighted_mean_pose(jax.nn.softmax(log_w1), poses[0][slots0]), steps)


def ancestry_path(estimate: str, poses: Array, ancestors: Array, log_w: Array,
                  best: Array, history: StepHistory | None = None) -> Array:
    """The path [T, 3] by ``estimate`` from the particles' poses [T, J, 3], ancestry [T, J],
    final log weights [J] and final best slot: "best" (``backtrack_path``), "mode" (the
    ``densest_particle``'s path through its ancestry), "smoothed" (``smoothed_mean_path``),
    "steps" (``smoothed_step_path``) or "local_steps" (``local_step_path`` over
    ``factor_cover``, from ``history``). ("mean", the other ``[filter] estimate``, is each
    frame's weighted mean, kept as the filter runs.)"""
    if estimate == "best":
        return backtrack_path(poses, ancestors, best)
    if estimate == "mode":
        return backtrack_path(poses, ancestors, map_particle("mode", poses[-1], log_w, best))
    if estimate == "mode_mean":
        return mode_mean_path(poses, ancestors, log_w)
    if estimate == "smoothed":
        return smoothed_mean_path(poses, ancestors, log_w)
    if estimate == "steps":
        return smoothed_step_path(poses, ancestors, log_w)
    if estimate == "local_steps":
        if history is None:
            raise ValueError("the estimate 'local_steps' needs the run's StepHistory")
        return local_step_path(poses, ancestors, history, factor_cover(poses, history))
    raise ValueError(f"no ancestry path for the estimate {estimate!r}: one of best, mode, "
                     "mode_mean, smoothed, steps, local_steps")


def map_particle(estimate: str, pose: Array, log_w: Array, best: Array | int) -> Array:
    """The slot [] whose map a run reports beside ``estimate``'s path, from the cloud [J, 3],
    its log weights [J] and its best slot: the ``densest_particle`` under "mode" and
    "mode_mean", so that the map is the one laid along (or at the centre of) the mode's path
    (after a revisit the best particle may be one that missed the old map and doubled it);
    else ``best``, the paper's map (the other averaged estimates are no one particle's path,
    so no map is theirs)."""
    if estimate in ("mode", "mode_mean"):
        return densest_particle(pose, log_w)
    return jnp.asarray(best, jnp.int32)
