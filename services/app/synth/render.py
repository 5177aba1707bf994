"""Ray-cast renderer of a :class:`services.app.synth.scene.Scene` for any rig of distorted cameras.

Each pixel's ray is the camera model's exact inverse (``CameraModel.unproject``, cached per camera),
so images come out with the real lens distortion. Rays are cast with Open3D's Embree scene from
``T_WC = T_WS @ T_SC``; the hit triangle and its barycentric coordinates give the atlas texel
(bilinear). Depth is the distance along the optical axis (z in C) of the ray through the pixel
centre: rays have z = 1 in C, so Embree's hit parameter is that depth directly.

Photometric model (:class:`RenderConfig`): albedo x Lambertian shade x exposure(t) x vignetting,
``supersample`` x ``supersample`` anti-aliasing, optional motion blur (sub-frame poses averaged over
the exposure), Gaussian read + shot noise, 8-bit output.
"""
from __future__ import annotations

import dataclasses
from typing import Literal

import cv2
import numpy as np
import open3d as o3d

from shared.camera import CameraCalib
from shared.config import param
from services.app.synth.kernels import build_rays, flatten_mips, shade_rays
from services.app.synth.scene import Scene

INVALID = 0xFFFFFFFF


@dataclasses.dataclass(frozen=True)
class RenderConfig:
    """Photometric knobs of the synthetic camera."""

    supersample: int = param(1, "rays per pixel along each image axis (edge anti-aliasing; textures are mip-filtered anyway)")
    mip_levels: int = param(4, "texture pyramid levels for footprint-based (trilinear) texture filtering (1 = off)")
    brightness_dn: float = param(235.0, "grey level of a fully lit albedo-1 surface at nominal exposure", "DN")
    read_noise_dn: float = param(1.5, "standard deviation of additive Gaussian sensor noise", "DN")
    shot_noise_gain: float = param(0.15, "shot noise: variance grows by this much per DN of signal", "DN")
    exposure_amplitude: float = param(0.12, "relative amplitude of slow exposure/gain changes (0 = constant)")
    exposure_period_s: float = param(9.0, "period of the slowest exposure change", "s")
    vignetting: float = param(0.25, "relative brightness lost at the image corners (cos^4-like falloff)")
    motion_blur_samples: int = param(1, "sub-frame renders averaged over the exposure (1 = no motion blur)")
    motion_blur_mode: Literal["render", "flow"] = param(
        "render", "'render': every sub-frame pose is ray cast (exact, motion_blur_samples x the cost); 'flow': the "
        "frame is rendered once and resampled along each pixel's image motion over the exposure (from its depth "
        "and the sub-frame poses; cheap, ignores what the motion uncovers)")
    exposure_time_s: float = param(0.004, "exposure time for motion blur", "s")
    exposure_jump_rate_hz: float = param(0.0, "auto-exposure jumps: mean rate of sudden gain changes per camera "
                                         "(Poisson; 0 = none)", "Hz")
    exposure_jump_amplitude: float = param(0.3, "auto-exposure jumps: each jump multiplies the gain by exp(u), u "
                                           "uniform in [-a, a]; the gain stays there until the next jump")
    seed: int = param(0, "seed of the noise and exposure pattern")


def sample_bilinear(img: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Bilinear samples (N,) float32 of ``img`` at pixel coords xy (N, 2) (x = column); edges replicated."""
    n, w = len(xy), 1024
    pad = np.zeros(((n + w - 1) // w * w, 2), np.float32)
    pad[:n] = xy
    out = cv2.remap(img, pad[:, 0].reshape(-1, w), pad[:, 1].reshape(-1, w), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.ravel()[:n].astype(np.float32)


def ray_grid(calib: CameraCalib, supersample: int) -> np.ndarray:
    """Rays (H*s * W*s, 3) float32 in C with z = 1, row-major over the supersampled pixel grid."""
    cam, s = calib.camera, supersample
    u = (np.arange(cam.width * s) + 0.5) / s - 0.5
    v = (np.arange(cam.height * s) + 0.5) / s - 0.5
    uu, vv = np.meshgrid(u, v)
    return cam.unproject(np.stack([uu.ravel(), vv.ravel()], 1)).astype(np.float32)


def vignette_map(calib: CameraCalib, strength: float) -> np.ndarray:
    """(H, W) float32 brightness factor: 1 at the principal point, 1 - strength at the farthest corner."""
    cam = calib.camera
    v, u = np.mgrid[0:cam.height, 0:cam.width]
    r2 = ((u - cam.cx) / cam.fx) ** 2 + ((v - cam.cy) / cam.fy) ** 2
    falloff = 1.0 / (1.0 + r2) ** 2  # cos^4 of the (pinhole) incidence angle
    lo = float(falloff.min())
    return (1.0 - strength * (1.0 - falloff) / max(1.0 - lo, 1e-9)).astype(np.float32)


def flow_blur(rad: np.ndarray, depth: np.ndarray, rays_C: np.ndarray, camera, T_WC: np.ndarray,
              T_WC_samples: list[np.ndarray], step: int = 4) -> np.ndarray:
    """Motion blur of an image rendered at pose ``T_WC``: the mean over the sub-frame poses of the image resampled
    along each pixel's motion. A pixel's 3D point (its ray ``rays_C`` (H*W, 3), z = 1, times ``depth``; far where
    there is none) projects to w_k(x) at sub-frame pose k; the sub-frame image is approximated by rad(2x - w_k(x))
    (the inverse of a locally smooth motion). The sub-frame poses are taken as evenly spaced in time; the motion
    is computed on every ``step``-th pixel and interpolated (it is smooth but at depth edges)."""
    h, w = rad.shape
    v, u = np.mgrid[0:h:step, 0:w:step]
    uv = np.stack([u.ravel(), v.ravel()], 1).astype(np.float64)
    z = np.nan_to_num(depth[::step, ::step].ravel().astype(np.float64), nan=1e3)
    rays = np.asarray(rays_C, np.float64).reshape(h, w, 3)[::step, ::step].reshape(-1, 3)
    p_W = (rays * z[:, None]) @ T_WC[:3, :3].T + T_WC[:3, 3]
    rad = rad.astype(np.float32)

    def motion(T):  # w_k(x) - x at sub-frame pose T, full resolution; none where the point leaves the view
        uv_k, ok = camera.project((p_W - T[:3, 3]) @ T[:3, :3])
        m = np.where(ok[:, None], uv_k - uv, 0.0).astype(np.float32).reshape(v.shape + (2,))
        return cv2.resize(m, (w, h), interpolation=cv2.INTER_LINEAR)

    # the image motion over an exposure of a few ms is close to linear in time: projected at the first and last
    # sub-frame pose only, interpolated for those in between
    first, last = motion(T_WC_samples[0]), motion(T_WC_samples[-1])
    gu, gv = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    out = np.zeros_like(rad)
    for s in np.linspace(0.0, 1.0, len(T_WC_samples), dtype=np.float32):
        m = (1.0 - s) * first + s * last
        out += cv2.remap(rad, gu - m[..., 0], gv - m[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out / len(T_WC_samples)


class Renderer:
    """Renders images and depth of ``cameras`` in ``scene``; cached rays per camera."""

    def __init__(self, scene: Scene, cameras: list[CameraCalib], cfg: RenderConfig | None = None):
        self.scene, self.cameras, self.cfg = scene, list(cameras), cfg or RenderConfig()
        if self.cfg.supersample < 1 or self.cfg.motion_blur_samples < 1:
            raise ValueError("render: supersample and motion_blur_samples must be >= 1")
        self._rc = o3d.t.geometry.RaycastingScene()
        self._rc.add_triangles(o3d.core.Tensor(scene.vertices.astype(np.float32)),
                               o3d.core.Tensor(scene.triangles.astype(np.uint32)))
        s = self.cfg.supersample
        self._rays = [ray_grid(c, s) for c in self.cameras]
        self._centre = [ray_grid(c, 1) if s > 1 else r for c, r in zip(self.cameras, self._rays)]
        self._vignette = [vignette_map(c, self.cfg.vignetting) for c in self.cameras]
        self._mips = [scene.atlas]
        for _ in range(max(self.cfg.mip_levels, 1) - 1):
            self._mips.append(cv2.pyrDown(self._mips[-1]))
        self._mip_buf = flatten_mips(self._mips)
        v = scene.vertices[scene.triangles]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        self._normals = (n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)).astype(np.float32)
        self._last_hit: tuple | None = None
        rng = np.random.default_rng([self.cfg.seed, 7])
        self._phase = rng.uniform(0, 2 * np.pi, (len(self.cameras), 2))
        self._jumps: dict[int, tuple[list, list, np.random.Generator]] = {}  # camera -> auto-exposure jump schedule

    @property
    def raycasting_scene(self) -> o3d.t.geometry.RaycastingScene:
        return self._rc

    def cast(self, rays_C: np.ndarray, T_WC: np.ndarray) -> dict[str, np.ndarray]:
        """Cast rays (N, 3) given in C from pose T_WC; returns t_hit (= z in C for z=1 rays), ids, uvs."""
        rays = np.empty((len(rays_C), 6), np.float32)
        build_rays(rays_C, np.asarray(T_WC[:3, :3], np.float32), np.asarray(T_WC[:3, 3], np.float32), rays)
        out = self._rc.cast_rays(o3d.core.Tensor.from_numpy(rays))
        return {"t_hit": out["t_hit"].numpy(), "ids": out["primitive_ids"].numpy(), "uvs": out["primitive_uvs"].numpy(),
                "rays": rays}

    def depth(self, T_WC: np.ndarray, cam_index: int = 0) -> np.ndarray:
        """(H, W) float32 depth along the optical axis [m]; NaN where the ray hits nothing."""
        cam = self.cameras[cam_index].camera
        key = (cam_index, np.asarray(T_WC, np.float64).tobytes())
        if self.cfg.supersample == 1 and self._last_hit is not None and self._last_hit[0] == key:
            z = self._last_hit[1]  # the image was just rendered from the same rays
        else:
            z = self.cast(self._centre[cam_index], T_WC)["t_hit"]
        return np.where(np.isfinite(z), z, np.nan).astype(np.float32).reshape(cam.height, cam.width)

    def radiance(self, T_WC: np.ndarray, cam_index: int = 0) -> np.ndarray:
        """(H, W) float32 noise-free irradiance (albedo x shade x vignetting, 1 = full), anti-aliased."""
        cam, s = self.cameras[cam_index].camera, self.cfg.supersample
        hit = self.cast(self._rays[cam_index], T_WC)
        self._last_hit = ((cam_index, np.asarray(T_WC, np.float64).tobytes()), hit["t_hit"])
        val = np.empty(len(hit["ids"]), np.float32)
        shade_rays(hit["ids"], hit["uvs"], hit["t_hit"], hit["rays"], self.scene.tri_uv, self.scene.tri_shade,
                   self._normals, *self._mip_buf, self.scene.texels_per_m / (cam.fx * s), val)
        hs, ws = cam.height * s, cam.width * s
        img = val.reshape(cam.height, s, cam.width, s).mean(axis=(1, 3)) if s > 1 else val.reshape(hs, ws)
        return img * self._vignette[cam_index]

    def radiance_reference(self, T_WC: np.ndarray, cam_index: int = 0) -> np.ndarray:
        """Plain-numpy version of :meth:`radiance` (without supersampling or vignetting): checks the kernel."""
        cam = self.cameras[cam_index].camera
        hit = self.cast(self._centre[cam_index], T_WC)
        ids = hit["ids"]
        ok = ids != INVALID
        idx = np.where(ok, ids, 0).astype(np.int64)
        tri = self.scene.tri_uv[idx]  # (N, 3, 2)
        b = hit["uvs"]
        tex = (1.0 - b[:, :1] - b[:, 1:2]) * tri[:, 0] + b[:, :1] * tri[:, 1] + b[:, 1:2] * tri[:, 2]
        albedo = self._sample_texture(tex, hit["t_hit"], self._centre[cam_index], idx, T_WC, cam.fx)
        return (albedo * (self.scene.tri_shade[idx] / 255.0) * ok).reshape(cam.height, cam.width)

    def _sample_texture(self, tex: np.ndarray, z: np.ndarray, rays_C: np.ndarray, idx: np.ndarray,
                        T_WC: np.ndarray, f_px: float) -> np.ndarray:
        """Albedo (N,) float32 [0, 255] at atlas coords ``tex``, blending the two mip levels whose texel size
        brackets the pixel's footprint on the surface (depth / f, stretched by 1/sqrt(cos incidence))."""
        n = len(tex)
        if len(self._mips) == 1:
            return sample_bilinear(self._mips[0], tex)
        d_W = rays_C @ np.asarray(T_WC[:3, :3], np.float32).T
        cos = np.abs(np.einsum("ij,ij->i", d_W, self._normals[idx])) / np.linalg.norm(d_W, axis=1)
        footprint = np.where(np.isfinite(z), z, 0.0) * self.scene.texels_per_m / f_px / np.sqrt(np.maximum(cos, 0.05))
        level = np.clip(np.log2(np.maximum(footprint, 1e-6)), 0.0, len(self._mips) - 1.0)
        out = np.zeros(n, np.float32)
        for k, mip in enumerate(self._mips):
            w = np.clip(1.0 - np.abs(level - k), 0.0, 1.0)
            sel = np.nonzero(w > 0)[0]
            if not len(sel):
                continue
            scale = 0.5 ** k
            uv = tex[sel] * scale  # cv2.pyrDown: texel j of level k is centred on texel 2^k j of level 0
            out[sel] += w[sel] * sample_bilinear(mip, uv)
        return out

    def exposure(self, t_s: float, cam_index: int = 0) -> float:
        """Exposure/gain factor at time t_s: slow changes times the auto-exposure jumps' gain."""
        a, p, ph = self.cfg.exposure_amplitude, self.cfg.exposure_period_s, self._phase[cam_index]
        slow = 1.0 + a * (0.7 * np.sin(2 * np.pi * t_s / p + ph[0]) + 0.3 * np.sin(2 * np.pi * t_s / (0.31 * p) + ph[1]))
        return float(slow * self._jump_gain(t_s, cam_index))

    def _jump_gain(self, t_s: float, cam_index: int) -> float:
        """Piecewise-constant gain of the auto-exposure jumps (1 without them): a Poisson schedule per camera,
        drawn from the config's seed and extended as time goes on, so that it depends on t_s alone."""
        rate = self.cfg.exposure_jump_rate_hz
        if rate <= 0 or t_s <= 0:
            return 1.0
        times, gains, rng = self._jumps.setdefault(
            cam_index, ([0.0], [1.0], np.random.default_rng([self.cfg.seed, 13, cam_index])))
        while times[-1] < t_s:
            times.append(times[-1] + rng.exponential(1.0 / rate))
            gains.append(float(np.exp(rng.uniform(-1.0, 1.0) * self.cfg.exposure_jump_amplitude)))
        return gains[int(np.searchsorted(times, t_s, side="right")) - 1]

    def blurred_radiance(self, T_WC_samples: list[np.ndarray], cam_index: int,
                         T_WC: np.ndarray | None = None) -> np.ndarray:
        """Radiance averaged over the exposure's sub-frame poses; ``T_WC``: the frame's own pose (the 'flow' mode
        renders there; default the middle sample)."""
        if len(T_WC_samples) == 1 or self.cfg.motion_blur_mode == "render":
            return sum(self.radiance(T, cam_index) for T in T_WC_samples) / len(T_WC_samples)
        mid = T_WC_samples[len(T_WC_samples) // 2] if T_WC is None else T_WC
        rad = self.radiance(mid, cam_index)
        return flow_blur(rad, self.depth(mid, cam_index), self._centre[cam_index], self.cameras[cam_index].camera, mid,
                         T_WC_samples)

    def image(self, T_WC_samples: list[np.ndarray], cam_index: int, t_s: float, rng: np.random.Generator,
              T_WC: np.ndarray | None = None) -> np.ndarray:
        """(H, W) uint8 image: radiance averaged over the sub-frame poses, exposure, noise."""
        rad = self.blurred_radiance(T_WC_samples, cam_index, T_WC)
        sig = rad * (self.cfg.brightness_dn * self.exposure(t_s, cam_index))
        std = np.sqrt(self.cfg.read_noise_dn ** 2 + self.cfg.shot_noise_gain * np.maximum(sig, 0.0))
        sig = sig + rng.standard_normal(sig.shape, dtype=np.float32) * std
        return np.clip(np.round(sig), 0, 255).astype(np.uint8)

    def render_rig(self, T_WS: np.ndarray, t_s: float, rng: np.random.Generator,
                   with_depth: tuple[int, ...] = (0,), blur_T_WS: list[np.ndarray] | None = None
                   ) -> tuple[list[np.ndarray], dict[int, np.ndarray]]:
        """Images of every camera at body pose T_WS (averaged over ``blur_T_WS`` sub-frame poses when given:
        motion blur) and depth of the cameras in ``with_depth`` at T_WS exactly."""
        poses = blur_T_WS or [T_WS]
        imgs, depths = [], {}
        for i, c in enumerate(self.cameras):
            imgs.append(self.image([T @ c.T_SC for T in poses], i, t_s, rng, T_WS @ c.T_SC))
            if i in with_depth:  # right after the image: reuses its rays when they are the same
                depths[i] = self.depth(T_WS @ c.T_SC, i)
        return imgs, depths
