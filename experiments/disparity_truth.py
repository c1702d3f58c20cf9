"""Dense stereo's disparity error on rendered frames against the truth, per disparity band, beside
what the front-end measures without it (``vo.disparity_noise``, frame to frame).

The truth: each SGBM point's ray (pair 0's left camera at the true pose) is marched through the
world's heightfield in 1 cm steps to the first sample under the surface, which gives its true
range and so its true disparity. Per band: the points, the median error (px), the true sigma
(1.4826 times the median absolute deviation), the frame-to-frame estimate from each frame and
the one before it (the true camera motion), their ratio, the mean and median range error (%),
and, for the points ``--edge-ratio`` keeps (``vo.stereo.drop_depth_edges``; inf by default,
which keeps all): their share and their mean absolute error against all points'. Bands under
200 points are left out.

    python -m experiments.disparity_truth --course maze --frames 20 80 140 200
    python -m experiments.disparity_truth --course mars-yard-a --frames 20 80 140 200 \
        --edge-ratio 0.5
"""

from __future__ import annotations

import argparse

import cv2
import numpy as np

from experiments.common import print_header
from gslam_jax.datasets.sim import simulate_odometry
from gslam_jax.sim.environments import world_for_course
from gslam_jax.sim.render import StereoRenderer
from gslam_jax.sim.world import World
from gslam_jax.vo.disparity_noise import DISPARITY_EDGES, DisparityNoise, temporal_residuals
from gslam_jax.vo.geometry import invert
from gslam_jax.vo.stereo import (DenseStereoParams, dense_disparity, disparity_to_points,
                                 drop_depth_edges)

MARCH_STEP = 0.01  # m
MAX_RANGE = 25.0   # m: the renderer's max_distance


def true_ranges(world: World, origin: np.ndarray, directions: np.ndarray,
                chunk: int = 2000) -> np.ndarray:
    """Range (m) along each unit direction from ``origin`` to the first sample under the
    heightfield (bilinear), NaN where none is within ``MAX_RANGE``."""
    heights = np.ascontiguousarray(world.height, np.float32)
    s = np.arange(0.3, MAX_RANGE, MARCH_STEP)
    out = np.full(len(directions), np.nan)
    for a in range(0, len(directions), chunk):
        d = directions[a:a + chunk]
        x = origin[0] + d[:, :1] * s
        y = origin[1] + d[:, 1:2] * s
        z = origin[2] + d[:, 2:3] * s
        mx = ((y - world.origin[1]) / world.resolution - 0.5).astype(np.float32)
        my = ((x - world.origin[0]) / world.resolution - 0.5).astype(np.float32)
        h = cv2.remap(heights, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                      borderValue=-1e3)
        below = z <= h
        out[a:a + chunk] = np.where(below.any(axis=1), s[below.argmax(axis=1)], np.nan)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--course", default="maze")
    ap.add_argument("--sim-seed", type=int, default=0)
    ap.add_argument("--frames", type=int, nargs="+", default=[20, 80, 140, 200],
                    help="frames scored (each also needs the one before it)")
    ap.add_argument("--max-depth", type=float, default=15.0, help="points kept, m of depth")
    ap.add_argument("--edge-ratio", type=float, default=float("inf"),
                    help="also score the points drop_depth_edges keeps at this ratio")
    args = ap.parse_args(argv)
    print_header([])
    cv2.setNumThreads(1)
    odo = simulate_odometry(args.course, args.sim_seed, max_frames=max(args.frames) + 1)
    world = world_for_course(odo.course, args.sim_seed)
    renderer = StereoRenderer(world, None, args.sim_seed)
    rig, params = renderer.rig, DenseStereoParams()
    fb = rig.fx * rig.baseline
    noise = DisparityNoise(forget=1.0)
    measured, truth, ranges, true_r, kept = [], [], [], [], []
    for t in args.frames:
        if t < 1:
            raise SystemExit(f"--frames: frame {t} has no frame before it")
        views = []
        for f in (t - 1, t):
            pose = odo.trajectory.poses[f]
            left, right = renderer.render_frame(pose, f, pairs=(0,))[0]
            views.append((dense_disparity(left, right, params), renderer.camera_poses(pose)[0][0]))
        (d0, t_w0), (d1, t_w1) = views
        noise.update(*temporal_residuals(d0, d1, invert(t_w0) @ t_w1, rig))
        pts = disparity_to_points(d1, rig, params.stride, max_range=args.max_depth)
        # which of these points drop_depth_edges keeps, in disparity_to_points' order
        sub = d1[::params.stride, ::params.stride].astype(np.float64)
        flags = np.isfinite(drop_depth_edges(d1, args.edge_ratio))[::params.stride,
                                                                    ::params.stride]
        flags = flags[np.isfinite(sub) & (sub > 0)]
        flags = flags[fb / sub[np.isfinite(sub) & (sub > 0)] <= args.max_depth]
        world_pts = pts @ t_w1[:3, :3].T + t_w1[:3, 3]
        rays = world_pts - t_w1[:3, 3]
        rng = np.linalg.norm(rays, axis=1)
        true = true_ranges(world, t_w1[:3, 3], rays / rng[:, None])
        ok = np.isfinite(true)
        d = fb / pts[ok, 2]
        measured.append(d)
        truth.append(d * rng[ok] / true[ok])  # disparity scales as 1 / range along a ray
        ranges.append(rng[ok])
        true_r.append(true[ok])
        kept.append(flags[ok])
    d, dt = np.concatenate(measured), np.concatenate(truth)
    rel = np.concatenate(ranges) / np.concatenate(true_r) - 1.0
    err = d - dt
    keep = np.concatenate(kept)
    band = np.searchsorted(DISPARITY_EDGES, dt)
    edges = np.concatenate([[0.0], DISPARITY_EDGES, [np.inf]])
    estimate = noise.band_sigmas()
    print(f"# {args.course} sim seed {args.sim_seed}, frames {args.frames}: {len(d)} points")
    print("band_px n median_err_px true_sigma_px frame_to_frame_px ratio range_err_mean_% "
          "range_err_median_% edge_kept_share mean_abs_err_px kept_mean_abs_err_px")
    for b in np.unique(band):
        m = band == b
        if m.sum() < 200:
            continue
        e = err[m]
        med = np.median(e)
        sigma = 1.4826 * np.median(np.abs(e - med))
        est = estimate[b] if noise.counts[b].sum() >= noise.min_samples else np.nan
        print(f"{edges[b]:.3g}-{edges[b + 1]:.3g} {m.sum()} {med:+.3f} {sigma:.3f} {est:.3f} "
              f"{est / sigma:.2f} {100 * rel[m].mean():+.2f} {100 * np.median(rel[m]):+.2f} "
              f"{keep[m].mean():.2f} {np.abs(e).mean():.3f} {np.abs(e[keep[m]]).mean():.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
