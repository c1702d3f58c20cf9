"""Stereo image renderer for simulated worlds: two rectified 512x384 grey pairs per frame.

Honest imagery for the OpenCV front-end: the images are rendered from the
world's surfaces, and the front-end sees nothing else.

Method (why not a per-pixel ray march): the world is a 2.5-D heightfield (``World.height`` at
0.05 m), and the robot is kept level (as the point sensor does), so every camera is yaw + pitch.
A *level* camera's image columns are vertical planes through the camera centre; in such a plane
the heightfield is a 1-D profile, and the classic front-to-back "voxel space" column sweep finds
the visible surface for every row of the column at once: march the column's ground ray with a
coarse-to-fine step (2.5 cm near, 1 % of the range far), project the surface height of each
sample to an image row, and the first sample whose running-minimum row reaches a pixel's row is
the one that pixel sees (a histogram + cumulative sum, no per-pixel march). The hit is then
interpolated linearly between that sample and the one before (sub-sample accuracy, so the
disparity of a rendered surface is that of its true depth). Cost: columns x samples
(~700 x 300) for visibility plus a few vectorised look-ups per pixel, instead of pixels x
samples. The level image (rendered with ``supersample`` x the focal length) is warped to the
pitched camera by the rotation homography K R K_level^-1, which is exact for a pure rotation.

Appearance: per-pixel world point -> material albedo, Lambertian shading with a fixed sun and
precomputed cast shadows (heightfield horizon test along the sun azimuth), and band-limited
multi-octave noise keyed to *world* coordinates (tri-planar: xy on the ground, xz/yz on object
sides), so texture is the same in every frame and every camera; octaves finer than the pixel
footprint fade out (no aliasing that would differ between the two eyes). Distance fog blends
into a sky whose faint clouds are keyed to direction only (zero disparity). A little sensor noise
(seeded per frame and camera) is added. Not rendered: the canopy layer (tree crowns) - the
arroyo's overhangs are missing from the images; Mars Yard worlds have none.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

from gslam_jax.vo.calib import RectifiedRig
from gslam_jax.vo.geometry import CAM_TO_ROBOT_AXES, make_transform
from gslam_jax.sim.world import Material, World

__all__ = ["RenderParams", "StereoRenderer", "camera_mounts"]

_ALBEDO = {Material.SAND: 0.55, Material.GRASS: 0.42, Material.ROCK: 0.36, Material.POLE: 0.75,
           Material.BIN: 0.5, Material.BUILDING: 0.62, Material.BUSH: 0.3, Material.TREE: 0.32,
           Material.SCRUB: 0.34}
_CONTRAST = {Material.SAND: 0.35, Material.GRASS: 0.5, Material.ROCK: 0.55, Material.POLE: 0.15,
             Material.BIN: 0.12, Material.BUILDING: 0.3, Material.BUSH: 0.6, Material.TREE: 0.5,
             Material.SCRUB: 0.6}
_TILE = 256  # texture tile side (px); tiles are periodic
_TILE_WAVELENGTH = 8.0  # px per texture wavelength in a tile


@dataclass(frozen=True)
class RenderParams:
    """Camera rig and rendering settings (metres, radians, pixels).

    Rig as the point sensor's (``sim.sensor.SensorParams``): two pairs yawed +-``camera_yaw``,
    pitched down ``camera_pitch``, 12 cm baseline, pair centres ``camera_height`` above the
    ground under the robot. ``octaves``: texture wavelengths (m) with their amplitudes.
    """

    width: int = 512
    height: int = 384
    focal_px: float = 370.0
    baseline: float = 0.12
    camera_height: float = 1.0
    camera_yaw: float = float(np.deg2rad(35.0))
    camera_pitch: float = float(np.deg2rad(16.0))
    supersample: float = 1.25
    near: float = 0.4
    near_step: float = 0.025
    far_step_frac: float = 0.01
    max_distance: float = 25.0
    fog_start: float = 14.0
    sun_azimuth: float = float(np.deg2rad(40.0))
    sun_elevation: float = float(np.deg2rad(50.0))
    ambient: float = 0.35
    noise_std: float = 1.0  # grey levels
    octaves: tuple[tuple[float, float], ...] = ((0.03, 0.6), (0.08, 0.8), (0.2, 1.0), (0.5, 0.8),
                                                (1.3, 0.6))

    def __post_init__(self) -> None:
        for name in ("width", "height", "focal_px", "baseline", "camera_height", "supersample",
                     "near", "near_step", "max_distance"):
            if not getattr(self, name) > 0:
                raise ValueError(f"RenderParams.{name} must be positive, got {getattr(self, name)}")
        if self.max_distance <= self.near:
            raise ValueError(f"RenderParams.max_distance ({self.max_distance}) must exceed "
                             f"near ({self.near})")


def camera_mounts(params: RenderParams) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per pair (left, right) 4x4 camera mounts T_robot_cam (OpenCV camera axes).

    Pair 0 looks left (+camera_yaw), pair 1 right; the right camera sits ``baseline`` along the
    left camera's x axis, so each pair is rectified by construction.
    """
    out = []
    for yaw in (params.camera_yaw, -params.camera_yaw):
        c, s = np.cos(yaw), np.sin(yaw)
        rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        cp, sp = np.cos(params.camera_pitch), np.sin(params.camera_pitch)
        ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])  # +pitch: nose down
        r = rz @ ry @ CAM_TO_ROBOT_AXES
        centre = np.array([0.0, 0.0, params.camera_height])
        left = centre - 0.5 * params.baseline * r[:, 0]
        out.append((make_transform(r, left), make_transform(r, left + params.baseline * r[:, 0])))
    return out


def _noise_tile(rng: np.random.Generator) -> np.ndarray:
    """Periodic band-limited noise (one octave), zero mean, unit std, float32 [_TILE, _TILE]."""
    f = np.fft.fftfreq(_TILE) * _TILE  # cycles per tile
    r = np.hypot(f[:, None], f[None, :])
    r0 = _TILE / _TILE_WAVELENGTH
    spec = np.fft.fft2(rng.standard_normal((_TILE, _TILE))) * np.exp(-0.5 * ((r - r0) / (0.45 * r0)) ** 2)
    tile = np.real(np.fft.ifft2(spec))
    return ((tile - tile.mean()) / tile.std()).astype(np.float32)


def _shadow_raster(height: np.ndarray, res: float, azimuth: float, elevation: float,
                   reach: float = 4.0) -> np.ndarray:
    """1 where a cell is in the sun, 0 in cast shadow (horizon test toward the sun), softened."""
    lit = np.ones(height.shape, bool)
    tan_el = np.tan(elevation)
    dx, dy = np.cos(azimuth), np.sin(azimuth)
    nx, ny = height.shape
    for k in range(1, int(reach / res) + 1):
        di, dj = int(round(k * dx)), int(round(k * dy))
        d = np.hypot(di, dj) * res
        if abs(di) >= nx or abs(dj) >= ny:
            break
        src = height[max(di, 0):nx + min(di, 0), max(dj, 0):ny + min(dj, 0)]
        dst = (slice(max(-di, 0), nx + min(-di, 0)), slice(max(-dj, 0), ny + min(-dj, 0)))
        lit[dst] &= src <= height[dst] + d * tan_el + 0.01
    return cv2.GaussianBlur(lit.astype(np.float32), (5, 5), 1.0)


class _Level(NamedTuple):
    f: float
    cx: float
    cy: float
    w: int
    h: int
    homography: np.ndarray  # pitched pixel -> level pixel


class StereoRenderer:
    """Renders the rig's images at ground-truth robot poses (x, y, theta) in one ``World``.

    Deterministic: the texture depends on ``seed`` only, the sensor noise on (seed, frame, view).
    """

    def __init__(self, world: World, params: RenderParams | None = None, seed: int = 0) -> None:
        self.world, self.params, self.seed = world, params or RenderParams(), int(seed)
        p, w = self.params, world
        self.mounts = camera_mounts(p)
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, 0x7E47]))
        self._tiles = [_noise_tile(rng) for _ in p.octaves]
        self._offsets = rng.uniform(0, _TILE, (len(p.octaves), 3, 2)).astype(np.float32)
        self._height = np.ascontiguousarray(w.height, np.float32)
        self._ground = np.ascontiguousarray(w.ground, np.float32)
        gx, gy = np.gradient(w.height.astype(np.float64), w.resolution)
        norm = np.sqrt(gx * gx + gy * gy + 1.0)
        nx, ny, nz = -gx / norm, -gy / norm, 1.0 / norm
        sun = np.array([np.cos(p.sun_elevation) * np.cos(p.sun_azimuth),
                        np.cos(p.sun_elevation) * np.sin(p.sun_azimuth), np.sin(p.sun_elevation)])
        lambert = np.clip(nx * sun[0] + ny * sun[1] + nz * sun[2], 0.0, 1.0)
        shadow = _shadow_raster(w.height, w.resolution, p.sun_azimuth, p.sun_elevation)
        shadow = np.where(nz * nz > 0.5, shadow, 1.0)  # cast shadows on near-level surfaces only
        self._shade = (p.ambient + (1.0 - p.ambient) * lambert * shadow).astype(np.float32)
        self._wx = (nx * nx).astype(np.float32)
        self._wz = (nz * nz).astype(np.float32)
        lut_a = np.full(256, 0.5, np.float32)
        lut_c = np.full(256, 0.3, np.float32)
        for m, v in _ALBEDO.items():
            lut_a[int(m)], lut_c[int(m)] = v, _CONTRAST[m]
        self._albedo, self._contrast = lut_a, lut_c
        self._material = np.ascontiguousarray(w.material, np.uint8)
        self._level = self._level_camera()
        s, ds = [p.near], 0.0
        while s[-1] < p.max_distance:
            ds = max(p.near_step, p.far_step_frac * s[-1])
            s.append(s[-1] + ds)
        self._s = np.asarray(s, np.float64)

    # ---- geometry -------------------------------------------------------------------------
    @property
    def rig(self) -> RectifiedRig:
        """The rectified pinhole model shared by all four cameras (both pairs)."""
        p = self.params
        k = np.array([[p.focal_px, 0.0, (p.width - 1) / 2], [0.0, p.focal_px, (p.height - 1) / 2],
                      [0.0, 0.0, 1.0]])
        p0 = np.hstack([k, np.zeros((3, 1))])
        p1 = np.hstack([k, np.array([[-p.focal_px * p.baseline], [0.0], [0.0]])])
        return RectifiedRig.from_projections(p0, p1, (p.width, p.height), "<sim renderer>")

    def _level_camera(self) -> _Level:
        p = self.params
        k = self.rig.k
        c, s = np.cos(p.camera_pitch), np.sin(p.camera_pitch)
        r_lp = np.array([[1.0, 0.0, 0.0], [0.0, c, s], [0.0, -s, c]])  # pitched ray -> level ray
        u = np.concatenate([np.arange(p.width), np.full(p.height, p.width - 1), np.arange(p.width),
                            np.zeros(p.height)])
        v = np.concatenate([np.zeros(p.width), np.arange(p.height), np.full(p.width, p.height - 1),
                            np.arange(p.height)])
        rays = r_lp @ np.linalg.inv(k) @ np.stack([u, v, np.ones_like(u)])
        f = p.focal_px * p.supersample
        px, py = f * rays[0] / rays[2], f * rays[1] / rays[2]
        cx, cy = -px.min() + 2.0, -py.min() + 2.0
        w, h = int(np.ceil(px.max() + cx + 2)), int(np.ceil(py.max() + cy + 2))
        k_l = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
        return _Level(f, cx, cy, w, h, k_l @ r_lp @ np.linalg.inv(k))

    def camera_poses(self, pose: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """World-frame 4x4 camera poses (left, right) of both pairs at robot pose (x, y, theta)."""
        x, y, th = (float(v) for v in pose)
        z = float(self._bilinear(self._ground, np.array([[x, y]]))[0])
        c, s = np.cos(th), np.sin(th)
        t_wr = make_transform(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), [x, y, z])
        return [(t_wr @ a, t_wr @ b) for a, b in self.mounts]

    def _raster_maps(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        w = self.world
        return (((y - w.origin[1]) / w.resolution - 0.5).astype(np.float32),
                ((x - w.origin[0]) / w.resolution - 0.5).astype(np.float32))

    def _bilinear(self, raster: np.ndarray, xy: np.ndarray) -> np.ndarray:
        mx, my = self._raster_maps(xy[..., 0].reshape(1, -1), xy[..., 1].reshape(1, -1))
        return cv2.remap(raster, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0]

    # ---- rendering ------------------------------------------------------------------------
    def render_view(self, t_world_cam: np.ndarray, rng: np.random.Generator | None = None
                    ) -> np.ndarray:
        """One uint8 [height, width] image from a camera pose whose only rotations are the rig's
        yaw and pitch (a level robot). ``rng`` adds sensor noise; None renders noise-free."""
        p, lv, w = self.params, self._level, self.world
        r = t_world_cam[:3, :3]
        fwd = r[:, 2].copy()
        fwd[2] = 0.0
        fwd /= np.linalg.norm(fwd)
        right = np.array([fwd[1], -fwd[0], 0.0])
        cam = t_world_cam[:3, 3]
        a = (np.arange(lv.w) - lv.cx) / lv.f  # level-camera column -> horizontal ray slope
        ca = np.sqrt(1.0 + a * a)
        dirs = (fwd[None, :2] + a[:, None] * right[None, :2]) / ca[:, None]  # [C, 2] unit
        s = self._s
        sx = cam[0] + dirs[:, 0, None] * s[None, :]
        sy = cam[1] + dirs[:, 1, None] * s[None, :]
        mx, my = self._raster_maps(sx, sy)
        hs = cv2.remap(self._height, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                       borderValue=-1e3).astype(np.float64)  # [C, K]
        rows = lv.cy - lv.f * (hs - cam[2]) * ca[:, None] / s[None, :]
        runmin = np.minimum.accumulate(rows, axis=1)
        C, K = rows.shape
        b = np.clip(np.ceil(runmin), 0, lv.h).astype(np.int64)
        hist = np.bincount((np.arange(C)[:, None] * (lv.h + 1) + b).ravel(),
                           minlength=C * (lv.h + 1)).reshape(C, lv.h + 1)
        covered = np.cumsum(hist[:, ::-1], axis=1)[:, ::-1]  # covered[c, j] = #{k: b_k >= j}
        kstar = np.ascontiguousarray(covered[:, 1:].T)  # [H, C]: first sample seen by row r
        hit = kstar < K
        k = np.minimum(kstar, K - 1)
        km = np.maximum(k - 1, 0)
        f32 = np.float32
        hs_t = np.ascontiguousarray(hs.T.astype(f32))  # [K, C]
        s32 = s.astype(f32)
        rr = np.arange(lv.h, dtype=f32)[:, None]
        slope = (f32(lv.cy) - rr) / (f32(lv.f) * ca[None, :].astype(f32))  # rise per ground m
        s_k, s_m = s32[k], s32[km]
        cz = f32(cam[2])
        d1 = cz + slope * s_m - np.take_along_axis(hs_t, km, 0)  # ray above surface before
        d2 = np.take_along_axis(hs_t, k, 0) - cz - slope * s_k  # ray below surface after
        t = np.where(k > 0, d1 / np.maximum(d1 + d2, f32(1e-9)), f32(1.0)).clip(0.0, 1.0)
        sh = s_m + t * (s_k - s_m)
        dx, dy = dirs[None, :, 0].astype(f32), dirs[None, :, 1].astype(f32)
        ox, oy = w.origin
        X = f32(cam[0]) + sh * dx
        Y = f32(cam[1]) + sh * dy
        Z = cz + slope * sh
        dist = sh * np.sqrt(f32(1.0) + slope * slope)
        inv = f32(1.0 / w.resolution)
        mx = (Y - f32(oy)) * inv - f32(0.5)
        my = (X - f32(ox)) * inv - f32(0.5)
        shade = cv2.remap(self._shade, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        wx = cv2.remap(self._wx, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        wz = cv2.remap(self._wz, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        kx = np.rint((f32(cam[1]) + s_k * dy - f32(oy)) * inv - f32(0.5))
        ky = np.rint((f32(cam[0]) + s_k * dx - f32(ox)) * inv - f32(0.5))
        mat = cv2.remap(self._material, kx, ky, cv2.INTER_NEAREST,
                        borderMode=cv2.BORDER_REPLICATE)
        # texture: tri-planar, octaves fade out below ~3 px of footprint
        dz = np.abs(slope) / np.sqrt(f32(1.0) + slope * slope)
        cos_inc = np.sqrt(wz) * dz + np.sqrt(np.clip(f32(1.0) - wz, 0, 1)) * f32(0.7)
        inv_foot = f32(lv.f) * np.sqrt(np.maximum(cos_inc, f32(0.12))) / dist
        wy = np.clip(f32(1.0) - wx - wz, 0.0, 1.0)
        side = bool((wz < 0.98).any())
        tex = np.zeros(k.shape, f32)
        planes = ((X, Y, wz), (Y, Z, wx), (X, Z, wy)) if side else ((X, Y, None),)
        for o, ((lam, amp), tile) in enumerate(zip(p.octaves, self._tiles)):
            fade = np.clip(inv_foot * f32(lam / 3.0) - f32(1.0), 0.0, 1.0)
            sc = f32(_TILE_WAVELENGTH / lam)
            acc = np.zeros(k.shape, f32)
            for i, (u, v, wt) in enumerate(planes):
                mu, mv = u * sc + self._offsets[o, i, 0], v * sc + self._offsets[o, i, 1]
                mu -= np.floor(mu * f32(1.0 / _TILE)) * f32(_TILE)
                mv -= np.floor(mv * f32(1.0 / _TILE)) * f32(_TILE)
                val = cv2.remap(tile, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
                acc += val if wt is None else wt * val
            tex += f32(amp) * fade * acc
        tex *= f32(1.0 / np.sqrt(sum(a * a for _, a in p.octaves)))
        value = self._albedo[mat] * shade * (f32(1.0) + self._contrast[mat] * np.tanh(tex))
        # sky: faint clouds keyed to direction only, and fog toward the horizon
        az = np.arctan2(dirs[:, 1], dirs[:, 0]).astype(f32)[None, :]
        el = np.arctan(slope)
        cu = np.broadcast_to(az * f32(60.0), k.shape)
        cu = cu - np.floor(cu * f32(1.0 / _TILE)) * f32(_TILE)
        cv = el * f32(60.0) + f32(11.0)
        cv -= np.floor(cv * f32(1.0 / _TILE)) * f32(_TILE)
        clouds = cv2.remap(self._tiles[-1], cu, cv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        sky = f32(0.8) + f32(0.03) * clouds - f32(0.1) * np.clip(el, 0, 1)
        fog = np.clip((dist - f32(p.fog_start)) * f32(1.0 / (p.max_distance - p.fog_start)),
                      0.0, 1.0) ** 1.5
        value = np.where(hit, (f32(1.0) - fog) * value + fog * f32(0.78), sky)
        level = f32(255.0) * value
        img = cv2.warpPerspective(level, lv.homography, (p.width, p.height),
                                  flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                  borderMode=cv2.BORDER_REPLICATE)
        if rng is not None and p.noise_std > 0:
            img += rng.normal(0.0, p.noise_std, img.shape).astype(np.float32)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)

    def render_frame(self, pose: np.ndarray, frame: int = 0, pairs: tuple[int, ...] = (0, 1)
                     ) -> list[tuple[np.ndarray, np.ndarray]]:
        """Rectified (left, right) uint8 pairs at robot pose (x, y, theta) for each of ``pairs``
        (0: left-looking, 1: right-looking); sensor noise seeded by (seed, frame, camera)."""
        poses = self.camera_poses(pose)
        out = []
        for i in pairs:
            views = []
            for j, t_wc in enumerate(poses[i]):
                rng = np.random.default_rng(np.random.SeedSequence([self.seed, int(frame), i, j]))
                views.append(self.render_view(t_wc, rng))
            out.append((views[0], views[1]))
        return out
