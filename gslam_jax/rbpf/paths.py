"""Trajectory estimates from the particles' per-frame poses and resampling ancestry: each
frame's weighted mean pose, the best particle's path through its ancestry (the paper's
estimate) and the particle smoother's mean path."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array, lax

__all__ = ["weighted_mean_pose", "backtrack_path", "smoothed_mean_path"]


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
