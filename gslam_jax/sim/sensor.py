"""The point sensor: two forward stereo pairs, ray cast against a ``World`` (paper 2, 6.3).

Geometry (LAGR Herminator): two stereo pairs with a 12 cm baseline, yawed +-35 deg so that together
they see about 140 deg, pitched down, cameras about 1 m above the ground. Rays are a jittered
subsample of the pixels (a few thousand per frame, fresh jitter every frame, so consecutive frames
sample different spots as a real disparity image would). Each ray is marched over the world
raster; the first pixel whose surface (or crown layer) the ray meets is the hit, so nearer objects
occlude farther ones. The hit height carries the surface's own per-point spread (``World.rough``),
then stereo error moves the point along the line of sight with depth std

    sigma_z = z^2 sigma_d / (f b)        (z: depth along the optical axis, b: baseline,
                                          f: focal length in pixels, sigma_d: disparity std)

Points drop out at random, more at close range on some vegetation (the correlator fails there,
paper 7.3); points beyond the range gate are not returned. Output: [N, 3] points in the gravity-
aligned robot frame (x forward, y left, z up, origin on the ground under the robot).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gslam_jax.sim.world import Material, World

__all__ = ["SensorParams", "PointSensor", "depth_noise_std"]


def depth_noise_std(depth: np.ndarray, focal_px: float, baseline: float,
                    disparity_std: float) -> np.ndarray:
    """Stereo depth std sigma_z = z^2 sigma_d / (f b) (metres)."""
    depth = np.asarray(depth, dtype=np.float64)
    return depth * depth * disparity_std / (focal_px * baseline)


@dataclass(frozen=True)
class SensorParams:
    """Stereo point-sensor settings (angles in radians, distances in metres)."""

    camera_height: float = 1.0
    baseline: float = 0.12
    focal_px: float = 370.0  # 512-px-wide images with ~70 deg horizontal field of view
    disparity_std: float = 0.2  # px
    camera_yaw: float = float(np.deg2rad(35.0))  # the pairs look at +-camera_yaw
    camera_pitch: float = float(np.deg2rad(16.0))  # downwards
    half_fov: float = float(np.deg2rad(70.0))  # combined field of view is 2 * half_fov
    min_elevation: float = float(np.deg2rad(-45.0))
    max_elevation: float = float(np.deg2rad(12.0))
    n_azimuth: int = 96
    n_ground_rows: int = 36  # rows spread evenly in ground distance (below the horizon)
    n_high_rows: int = 6  # rows from just below the horizon up to max_elevation
    min_range: float = 0.5
    max_range: float = 10.0  # range gate, horizontal metres
    near_step: float = 0.05  # ray-march step up to near_limit, then far_step
    far_step: float = 0.1
    near_limit: float = 4.0
    dropout: float = 0.05
    # (material, range below which, probability): stereo fails on some vegetation up close
    close_dropouts: tuple[tuple[int, float, float], ...] = field(
        default=((int(Material.SCRUB), 2.5, 0.6), (int(Material.BUSH), 1.5, 0.3)))

    def __post_init__(self) -> None:
        for name in ("camera_height", "baseline", "focal_px", "max_range", "near_step",
                     "far_step"):
            if not getattr(self, name) > 0:
                raise ValueError(f"SensorParams.{name} must be positive, got {getattr(self, name)}")
        if not 0 <= self.dropout < 1:
            raise ValueError(f"SensorParams.dropout must be in [0, 1), got {self.dropout}")
        if self.min_range >= self.max_range:
            raise ValueError(f"SensorParams.min_range ({self.min_range}) must be below "
                             f"max_range ({self.max_range})")


class PointSensor:
    """Ray-casting point sensor for one world; ``observe(pose, rng)`` gives one frame."""

    def __init__(self, world: World, params: SensorParams | None = None) -> None:
        self.world = world
        self.params = p = params or SensorParams()
        self._s = np.concatenate([np.arange(p.min_range, p.near_limit, p.near_step),
                                  np.arange(p.near_limit, p.max_range + p.far_step, p.far_step)]
                                 ).astype(np.float32)
        self._ds = np.diff(self._s, prepend=self._s[0]).astype(np.float32)
        lo = max(p.camera_height / np.tan(-p.min_elevation), p.min_range)
        self._ground_r = np.linspace(lo, p.max_range, p.n_ground_rows)
        self._high_el = np.linspace(-np.arctan2(p.camera_height, p.max_range * 1.5),
                                    p.max_elevation, p.n_high_rows)
        self._w: World | None = None  # the raster rays read, bound at the first frame

    def _bind(self, world: World) -> None:
        """Read rays from the dense raster ``world`` (the world itself, or the window of a
        tiled world around the robot: ``World.local``)."""
        self._w = world
        self._height = np.ascontiguousarray(world.height, np.float32).ravel()
        self._canopy = world.has_canopy
        self._clo = np.ascontiguousarray(world.canopy_lo, np.float32).ravel()
        self._chi = np.ascontiguousarray(world.canopy_hi, np.float32).ravel()
        self._s_px = self._s / np.float32(world.resolution)
        self._ny = world.shape[1]
        self._n = world.shape[0] * world.shape[1]

    @property
    def rays_per_frame(self) -> int:
        return self.params.n_azimuth * (self.params.n_ground_rows + self.params.n_high_rows)

    def _rays(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Jittered (azimuth, elevation) of every ray, [R] each."""
        p = self.params
        n_az = p.n_azimuth
        daz = 2 * p.half_fov / n_az
        az = -p.half_fov + (np.arange(n_az) + 0.5) * daz
        dr = np.diff(self._ground_r).mean() if p.n_ground_rows > 1 else 0.0
        r = self._ground_r[:, None] + rng.uniform(-0.5, 0.5, (p.n_ground_rows, n_az)) * dr
        el_ground = -np.arctan2(p.camera_height, np.maximum(r, 0.1))
        de = np.diff(self._high_el).mean() if p.n_high_rows > 1 else 0.0
        el_high = self._high_el[:, None] + rng.uniform(-0.5, 0.5, (p.n_high_rows, n_az)) * de
        el = np.concatenate([el_ground, el_high]).ravel()
        n_rows = p.n_ground_rows + p.n_high_rows
        az_all = (az[None, :] + rng.uniform(-0.5, 0.5, (n_rows, n_az)) * daz).ravel()
        return az_all, np.clip(el, p.min_elevation, p.max_elevation)

    def observe(self, pose: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Points [N, 3] (robot frame) seen from the ground-truth world pose (x, y, theta)."""
        p = self.params
        x, y, th = (float(v) for v in pose)
        local = self.world.local(x, y, float(self._s[-1]) + self.world.resolution)
        if local is not self._w:
            self._bind(local)
        w = local
        g_robot = float(w.ground_at(np.array([x, y])))
        cam_z = g_robot + p.camera_height
        az, el = self._rays(rng)
        tan_el = np.tan(el).astype(np.float32)
        ca = np.cos(az + th).astype(np.float32)
        sa = np.sin(az + th).astype(np.float32)
        fx = np.float32((x - w.origin[0]) / w.resolution)
        fy = np.float32((y - w.origin[1]) / w.resolution)
        ix = (fx + ca[:, None] * self._s_px[None, :]).astype(np.int32)
        iy = (fy + sa[:, None] * self._s_px[None, :]).astype(np.int32)
        flat = ix * np.int32(self._ny) + iy
        np.clip(flat, 0, self._n - 1, out=flat)
        ray_z = np.float32(cam_z) + tan_el[:, None] * self._s[None, :]
        surf = self._height[flat]
        hit = ray_z <= surf
        upward = np.flatnonzero(el > -0.1)
        if self._canopy and upward.size:
            fu, zu = flat[upward], ray_z[upward]
            hit[upward] |= (zu >= self._clo[fu]) & (zu <= self._chi[fu])
        k = np.argmax(hit, axis=1)
        rows = np.flatnonzero(hit[np.arange(hit.shape[0]), k])
        k = k[rows]
        s_k, z_k = self._s[k], ray_z[rows, k]
        top = surf[rows, k]
        kp = np.maximum(k - 1, 0)
        z_prev = ray_z[rows, kp]
        # from above onto a top surface: interpolate the crossing; into a side face: the face
        from_above = (z_prev > top) & (top >= z_k) & (k > 0)
        frac = np.where(from_above, (z_prev - top) / np.maximum(z_prev - z_k, 1e-6), 0.5)
        s_hit = np.where(k > 0, self._s[kp] + np.clip(frac, 0, 1) * self._ds[k], s_k)
        z_hit = np.where(from_above, top, np.float32(cam_z) + tan_el[rows] * s_hit)
        cell = flat[rows, k]
        rough = w.rough.ravel()[cell]
        ground = w.ground.ravel()[cell]
        z_hit = np.maximum(z_hit + rng.normal(0.0, 1.0, rows.size) * rough, ground)
        # the surface point in the robot frame, camera at (0, 0, camera_height)
        a = az[rows]
        px, py, pz = s_hit * np.cos(a), s_hit * np.sin(a), z_hit - g_robot
        keep = self._dropouts(rng, s_hit, w.material.ravel()[cell])
        px, py, pz, a = px[keep], py[keep], pz[keep], a[keep]
        # stereo error along the line of sight, sigma from the depth on the optical axis
        vz = pz - p.camera_height
        rng_los = np.sqrt(px * px + py * py + vz * vz)
        yaw = np.where(a >= 0, p.camera_yaw, -p.camera_yaw)
        cp, sp = np.cos(p.camera_pitch), np.sin(p.camera_pitch)
        depth = (px * np.cos(yaw) * cp + py * np.sin(yaw) * cp - vz * sp)
        depth = np.maximum(depth, 0.05)
        sigma = depth_noise_std(depth, p.focal_px, p.baseline, p.disparity_std)
        d_rng = rng.normal(0.0, 1.0, px.size) * sigma * rng_los / depth
        scale = 1.0 + d_rng / rng_los
        out = np.stack([px * scale, py * scale, p.camera_height + vz * scale], axis=1)
        horiz = np.hypot(out[:, 0], out[:, 1])
        return out[(horiz <= p.max_range) & (horiz >= p.min_range)]

    def _dropouts(self, rng: np.random.Generator, rng_h: np.ndarray,
                  material: np.ndarray) -> np.ndarray:
        p = self.params
        prob = np.full(rng_h.shape, p.dropout)
        for mat, near, pr in p.close_dropouts:
            prob = np.where((material == mat) & (rng_h < near), np.maximum(prob, pr), prob)
        return rng.random(rng_h.shape) >= prob
