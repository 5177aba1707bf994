"""Procedural training scenes for the depth networks: a textured room with boxes and spheres, ray cast
exactly (per-pixel ground-truth depth), so that stereo pairs and posed multi-view sets can be rendered
from any camera, including the distorted EuRoC cameras (rays from ``CameraModel.unproject``).

These scenes are disjoint from the evaluation replicas by construction (different generator, own seeds).
Textures are solid (a function of the 3D point), so every view of a surface sees the same pattern:
a sum of random plane waves plus hashed cell noise at two scales; some objects get almost no contrast
so that the networks see textureless regions (where their sigma must grow).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

N_WAVES = 12


@dataclass(frozen=True)
class Scene:
    """Axis-aligned boxes (the first one is the room, seen from inside) and spheres, with textures."""

    box_lo: np.ndarray  # (B, 3) [m]
    box_hi: np.ndarray  # (B, 3) [m]
    sph_c: np.ndarray  # (S, 3) [m]
    sph_r: np.ndarray  # (S,) [m]
    wave_dir: np.ndarray  # (O, N_WAVES, 3) unit directions, O = B + S objects
    wave_k: np.ndarray  # (O, N_WAVES) [rad/m]
    wave_phase: np.ndarray  # (O, N_WAVES) [rad]
    cell_scale: np.ndarray  # (O, 2) cells per metre of the two noise octaves
    albedo: np.ndarray  # (O,) mean brightness in [0, 1]
    contrast: np.ndarray  # (O,) texture amplitude
    light_W: np.ndarray  # (3,) unit direction towards the light

    @property
    def n_objects(self) -> int:
        return len(self.box_lo) + len(self.sph_r)


def random_scene(rng: np.random.Generator, n_boxes: int = 6, n_spheres: int = 3) -> Scene:
    """A room of 3-8 m with boxes on the floor/in the air and spheres; all textures random."""
    size = rng.uniform([3.0, 3.0, 2.5], [8.0, 8.0, 4.0])
    lo = [-size / 2 * np.array([1, 1, 0])]
    hi = [size / 2 * np.array([1, 1, 0]) + np.array([0, 0, size[2]])]
    for _ in range(n_boxes):
        ext = rng.uniform(0.2, 1.2, 3)
        c = rng.uniform(-size / 2 + 0.3, size / 2 - 0.3) * np.array([1, 1, 0])
        c[2] = rng.choice([ext[2] / 2, rng.uniform(0.5, size[2] - 0.5)])
        lo.append(c - ext / 2)
        hi.append(c + ext / 2)
    sph_c = rng.uniform(-size / 2 + 0.5, size / 2 - 0.5, (n_spheres, 3)) * np.array([1, 1, 0])
    sph_c[:, 2] = rng.uniform(0.4, size[2] - 0.4, n_spheres)
    sph_r = rng.uniform(0.15, 0.6, n_spheres)
    n_obj = 1 + n_boxes + n_spheres
    d = rng.normal(size=(n_obj, N_WAVES, 3))
    d /= np.linalg.norm(d, axis=2, keepdims=True)
    k = np.exp(rng.uniform(np.log(3.0), np.log(80.0), (n_obj, N_WAVES)))
    contrast = np.where(rng.random(n_obj) < 0.15, rng.uniform(0.0, 0.04, n_obj), rng.uniform(0.2, 0.5, n_obj))
    light = rng.normal(size=3) + np.array([0, 0, 2.0])
    return Scene(np.array(lo), np.array(hi), sph_c, sph_r, d, k, rng.uniform(0, 2 * np.pi, (n_obj, N_WAVES)),
                 np.exp(rng.uniform(np.log(4.0), np.log(30.0), (n_obj, 2))), rng.uniform(0.25, 0.75, n_obj),
                 contrast, light / np.linalg.norm(light))


def raycast(scene: Scene, origin_W: np.ndarray, dirs_W: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First hit along rays ``origin + t dirs`` (dirs (P,3), not necessarily unit): t (P,), object (P,), normal (P,3)."""
    o = np.asarray(origin_W, np.float64)
    d = np.where(np.abs(dirs_W) < 1e-12, 1e-12, dirs_W)
    inv = 1.0 / d  # (P,3)
    t1 = (scene.box_lo[None] - o) * inv[:, None]  # (P,B,3)
    t2 = (scene.box_hi[None] - o) * inv[:, None]
    tnear = np.minimum(t1, t2).max(axis=2)
    tfar = np.maximum(t1, t2).min(axis=2)
    hit = (tnear <= tfar) & (tfar > 1e-6)
    t_box = np.where(tnear > 1e-6, tnear, np.inf)
    t_box[:, 0] = tfar[:, 0]  # the room is seen from inside: its exit point
    t_box = np.where(hit, t_box, np.inf)
    oc = o[None] - scene.sph_c  # (S,3)
    a = (d * d).sum(1)[:, None]
    b = d @ oc.T  # (P,S)
    c = (oc * oc).sum(1)[None] - scene.sph_r[None] ** 2
    disc = b * b - a * c
    t_sph = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / a, np.inf)
    t_sph = np.where(t_sph > 1e-6, t_sph, np.inf)
    t_all = np.concatenate([t_box, t_sph], axis=1)
    obj = t_all.argmin(axis=1)
    t = t_all[np.arange(len(obj)), obj]
    p = o + t[:, None] * d
    nb = len(scene.box_lo)
    normal = np.zeros_like(p)
    is_box = obj < nb
    if is_box.any():
        ob = obj[is_box]
        pb = p[is_box]
        dist = np.stack([np.abs(pb - scene.box_lo[ob]), np.abs(pb - scene.box_hi[ob])], axis=1)  # (Q,2,3)
        flat = dist.reshape(len(pb), 6).argmin(axis=1)
        side, axis = flat // 3, flat % 3
        n = np.zeros_like(pb)
        n[np.arange(len(pb)), axis] = np.where(side == 0, -1.0, 1.0)
        n[ob == 0] *= -1.0  # room walls face inwards
        normal[is_box] = n
    if (~is_box).any():
        os_ = obj[~is_box] - nb
        n = p[~is_box] - scene.sph_c[os_]
        normal[~is_box] = n / np.linalg.norm(n, axis=1, keepdims=True)
    return t, obj, normal


def _cell_noise(p: np.ndarray, scale: np.ndarray, salt: np.ndarray) -> np.ndarray:
    ijk = np.floor(p * scale[:, None]).astype(np.int64)
    h = (ijk[:, 0] * 73856093) ^ (ijk[:, 1] * 19349663) ^ (ijk[:, 2] * 83492791) ^ (salt * 2654435761)
    return ((h % 1009) / 1008.0 - 0.5).astype(np.float64)


def shade(scene: Scene, p: np.ndarray, obj: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Brightness in [0, 1] of surface points p (P,3) of objects obj with normals."""
    tex = np.zeros(len(p))
    for j in range(N_WAVES):  # a loop over the plane waves, each vectorised over all points
        tex += np.sin(scene.wave_k[obj, j] * (p * scene.wave_dir[obj, j]).sum(1) + scene.wave_phase[obj, j])
    tex = tex / np.sqrt(N_WAVES / 2) * 0.5
    tex += _cell_noise(p, scene.cell_scale[obj, 0], obj) + 0.6 * _cell_noise(p, scene.cell_scale[obj, 1], obj + 97)
    light = 0.35 + 0.65 * np.clip(normal @ scene.light_W, 0.0, 1.0)
    return np.clip((scene.albedo[obj] + scene.contrast[obj] * tex) * light, 0.0, 1.0)


def render_rays(scene: Scene, T_WC: np.ndarray, rays_C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Brightness (P,) and z-depth in C (P,) of rays given in C with z = 1."""
    dirs_W = rays_C @ T_WC[:3, :3].T
    t, obj, normal = raycast(scene, T_WC[:3, 3], dirs_W)
    p = T_WC[:3, 3] + t[:, None] * dirs_W
    return shade(scene, p, obj, normal), t  # rays have z = 1 in C, so t is the z-depth


def render_pinhole(scene: Scene, T_WC: np.ndarray, K: np.ndarray, size: tuple[int, int], supersample: int = 2,
                   noise_std: float = 2.0, rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """uint8 image (h,w) (box-filtered over supersample^2 rays per pixel, plus Gaussian noise [grey levels])
    and float32 z-depth (h,w) at pixel centres."""
    w, h = size
    s = supersample
    v, u = np.mgrid[0:h * s, 0:w * s]
    uu = (u + 0.5) / s - 0.5
    vv = (v + 0.5) / s - 0.5
    Ki = np.linalg.inv(K)
    rays = np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)], 1) @ Ki.T
    img, _ = render_rays(scene, T_WC, rays)
    img = img.reshape(h, s, w, s).mean(axis=(1, 3))
    v, u = np.mgrid[0:h, 0:w]
    _, depth = render_rays(scene, T_WC, np.stack([u.ravel(), v.ravel(), np.ones(u.size)], 1).astype(float) @ Ki.T)
    if rng is not None and noise_std > 0:
        img = img * 255.0 + rng.normal(0, noise_std, img.shape)
    else:
        img = img * 255.0
    return np.clip(img, 0, 255).astype(np.uint8), depth.reshape(h, w).astype(np.float32)


def look_at(position: np.ndarray, target: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """T_WC of a camera at ``position`` looking at ``target`` (world z up, image y down), rolled about its axis."""
    z = target - position
    z = z / np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    if np.linalg.norm(x) < 1e-6:
        x = np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll), np.sin(roll)
    R = np.stack([c * x + s * y, -s * x + c * y, z], axis=1)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, position
    return T


def _inside_object(scene: Scene, p: np.ndarray, margin: float = 0.3) -> bool:
    in_box = ((p > scene.box_lo[1:] - margin) & (p < scene.box_hi[1:] + margin)).all(axis=1).any()
    return bool(in_box or (np.linalg.norm(p - scene.sph_c, axis=1) < scene.sph_r + margin).any())


def random_camera(scene: Scene, rng: np.random.Generator) -> np.ndarray:
    """A camera pose inside the room (0.5 m from the walls), looking at a random point of the room."""
    lo, hi = scene.box_lo[0] + 0.5, scene.box_hi[0] - 0.5
    pos = rng.uniform(lo, hi)
    while _inside_object(scene, pos):
        pos = rng.uniform(lo, hi)
    target = rng.uniform(scene.box_lo[0], scene.box_hi[0])
    while np.linalg.norm(target - pos) < 1.0:
        target = rng.uniform(scene.box_lo[0], scene.box_hi[0])
    return look_at(pos, target, rng.normal(0, 0.15))
