"""Procedural training scenes for the depth networks: a textured room with boxes and spheres, ray cast
exactly (per-pixel ground-truth depth), so that stereo pairs and posed multi-view sets can be rendered
from any camera, including the distorted EuRoC cameras (rays from ``CameraModel.unproject``).

These scenes are disjoint from the evaluation replicas by construction (different generator, own seeds).
Textures are a function of the 3D point (and of the face's axis), so every view of a surface sees the same
pattern. Two styles:

- **solid** (``random_scene``): a sum of random plane waves plus hashed cell noise at two scales; some objects
  get almost no contrast so that the networks see textureless regions (where their sigma must grow);
- **dressed** (``dress``, for the multi-view training set): each object carries a material image of
  tools/depth/materials.py (photographs, procedural patterns, combinations, textureless paint) laid on its faces
  by planar projection along the face's dominant axis, at 0.4-6 m per image, mirror-tiled; plus thin bars and
  objects close to the camera walk (``add_objects``) and a random ambient light level.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

N_WAVES = 12
LOD_LEVELS = 5  # blurred copies of a material image, so that far or grazing surfaces do not alias


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
    textures: np.ndarray | None = None  # (O, L, S, S) material images (dressed style) blurred to L levels of detail
    #                                     (level l: Gaussian sigma 2^(l-1) texels, l = 0 sharp); None: solid waves
    texel_m: np.ndarray | None = None  # (O,) metres per texel of the material image
    tex_offset: np.ndarray | None = None  # (O, 2) texel offset of each object's image
    ambient: float = 0.35  # share of the light that does not depend on the normal

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


def _object_params(rng, n: int) -> dict[str, np.ndarray]:
    """Solid-texture parameters of n objects (the per-object arrays of Scene)."""
    d = rng.normal(size=(n, N_WAVES, 3))
    d /= np.linalg.norm(d, axis=2, keepdims=True)
    return {"wave_dir": d, "wave_k": np.exp(rng.uniform(np.log(3.0), np.log(80.0), (n, N_WAVES))),
            "wave_phase": rng.uniform(0, 2 * np.pi, (n, N_WAVES)),
            "cell_scale": np.exp(rng.uniform(np.log(4.0), np.log(30.0), (n, 2))),
            "albedo": rng.uniform(0.25, 0.75, n), "contrast": rng.uniform(0.2, 0.5, n)}


def add_objects(scene: Scene, rng, box_lo=None, box_hi=None, sph_c=None, sph_r=None) -> Scene:
    """The scene with more boxes and spheres (solid texture parameters drawn for them); a solid scene only
    (dress it afterwards)."""
    if scene.textures is not None:
        raise ValueError("add_objects: add objects before dress()")
    box_lo = np.zeros((0, 3)) if box_lo is None else np.asarray(box_lo, float).reshape(-1, 3)
    box_hi = np.zeros((0, 3)) if box_hi is None else np.asarray(box_hi, float).reshape(-1, 3)
    sph_c = np.zeros((0, 3)) if sph_c is None else np.asarray(sph_c, float).reshape(-1, 3)
    sph_r = np.zeros(0) if sph_r is None else np.asarray(sph_r, float).reshape(-1)
    nb = len(scene.box_lo)
    new_b, new_s = _object_params(rng, len(box_lo)), _object_params(rng, len(sph_r))
    fields = {}
    for k in new_b:
        old = getattr(scene, k)
        fields[k] = np.concatenate([old[:nb], new_b[k], old[nb:], new_s[k]])
    return dataclasses.replace(scene, box_lo=np.concatenate([scene.box_lo, box_lo]),
                               box_hi=np.concatenate([scene.box_hi, box_hi]),
                               sph_c=np.concatenate([scene.sph_c, sph_c]), sph_r=np.concatenate([scene.sph_r, sph_r]),
                               **fields)


def random_bars(scene: Scene, rng, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n thin axis-aligned bars (1-6 cm thick, 0.3-2.5 m long: legs, poles, shelves' edges) inside the room."""
    room_lo, room_hi = scene.box_lo[0], scene.box_hi[0]
    lo, hi = [], []
    for _ in range(n):
        ext = rng.uniform(0.01, 0.06, 3)
        ext[int(rng.integers(3))] = rng.uniform(0.3, 2.5)
        c = rng.uniform(room_lo + ext / 2, room_hi - ext / 2)
        lo.append(c - ext / 2)
        hi.append(c + ext / 2)
    return np.array(lo).reshape(-1, 3), np.array(hi).reshape(-1, 3)


def material_levels(image: np.ndarray) -> np.ndarray:
    """(S,S) material image -> (LOD_LEVELS,S,S) in [0, 1]: itself and Gaussian blurs of 2^(l-1) texels."""
    import cv2

    t = np.asarray(image, np.float32).clip(0, 1)
    return np.stack([t] + [cv2.GaussianBlur(t, (0, 0), 2.0 ** (lvl - 1), borderType=cv2.BORDER_REFLECT)
                           for lvl in range(1, LOD_LEVELS)])


def dress(scene: Scene, rng, photos: list[np.ndarray], size: int = 256) -> Scene:
    """The same geometry with a material image per object (tools/depth/materials.py) and a random ambient."""
    from tools.depth.materials import random_material

    n = scene.n_objects
    tex = np.stack([material_levels(random_material(rng, photos, size, size)) for _ in range(n)])
    extent = np.exp(rng.uniform(np.log(0.4), np.log(6.0), n))  # metres covered by one image
    return dataclasses.replace(scene, textures=tex, texel_m=extent / size,
                               tex_offset=rng.uniform(0, 2 * size, (n, 2)), ambient=float(rng.uniform(0.15, 0.6)))


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


def _sample_material(scene: Scene, p: np.ndarray, obj: np.ndarray, normal: np.ndarray,
                     footprint_m: np.ndarray | None) -> np.ndarray:
    """Albedo of points p from their object's material image, projected along the normal's dominant axis,
    mirror-tiled (no seams), bilinear, from the level of detail whose blur matches the pixel's footprint on the
    surface [m] (None: the sharp level)."""
    size = scene.textures.shape[-1]
    level = np.zeros(len(p), np.int64)
    if footprint_m is not None:
        ratio = footprint_m / scene.texel_m[obj]  # texels per pixel
        level = np.clip(np.floor(np.log2(np.maximum(ratio, 1e-9)) + 1.0), 0, scene.textures.shape[1] - 1).astype(np.int64)
    axis = np.abs(normal).argmax(axis=1)
    a = np.where(axis == 0, 1, 0)  # the two coordinates of the face's plane
    b = np.where(axis == 2, 1, 2)
    rows = np.arange(len(p))
    u = p[rows, a] / scene.texel_m[obj] + scene.tex_offset[obj, 0]
    v = p[rows, b] / scene.texel_m[obj] + scene.tex_offset[obj, 1]

    def mirror(t):
        t = np.mod(t, 2 * size)
        return np.where(t >= size, 2 * size - 1 - t, t)

    u0, v0 = np.floor(u), np.floor(v)
    fu, fv = u - u0, v - v0
    out = np.zeros(len(p))
    for du, dv, wgt in ((0, 0, (1 - fu) * (1 - fv)), (1, 0, fu * (1 - fv)), (0, 1, (1 - fu) * fv), (1, 1, fu * fv)):
        iu = mirror(u0 + du).astype(np.int64).clip(0, size - 1)
        iv = mirror(v0 + dv).astype(np.int64).clip(0, size - 1)
        out += wgt * scene.textures[obj, level, iv, iu]
    return out


def shade(scene: Scene, p: np.ndarray, obj: np.ndarray, normal: np.ndarray,
          footprint_m: np.ndarray | None = None) -> np.ndarray:
    """Brightness in [0, 1] of surface points p (P,3) of objects obj with normals; footprint_m: the size of the
    pixel on the surface [m] (dressed scenes pick the material's level of detail by it)."""
    light = scene.ambient + (1 - scene.ambient) * np.clip(normal @ scene.light_W, 0.0, 1.0)
    if scene.textures is not None:
        return np.clip(_sample_material(scene, p, obj, normal, footprint_m) * light, 0.0, 1.0)
    tex = np.zeros(len(p))
    for j in range(N_WAVES):  # a loop over the plane waves, each vectorised over all points
        tex += np.sin(scene.wave_k[obj, j] * (p * scene.wave_dir[obj, j]).sum(1) + scene.wave_phase[obj, j])
    tex = tex / np.sqrt(N_WAVES / 2) * 0.5
    tex += _cell_noise(p, scene.cell_scale[obj, 0], obj) + 0.6 * _cell_noise(p, scene.cell_scale[obj, 1], obj + 97)
    return np.clip((scene.albedo[obj] + scene.contrast[obj] * tex) * light, 0.0, 1.0)


def render_rays(scene: Scene, T_WC: np.ndarray, rays_C: np.ndarray,
                pixel_rad: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Brightness (P,) and z-depth in C (P,) of rays given in C with z = 1; pixel_rad: the angle one pixel spans
    [rad] (1/f), for the dressed materials' level of detail."""
    dirs_W = rays_C @ T_WC[:3, :3].T
    t, obj, normal = raycast(scene, T_WC[:3, 3], dirs_W)
    p = T_WC[:3, 3] + t[:, None] * dirs_W
    footprint = None
    if pixel_rad is not None:
        length = np.linalg.norm(dirs_W, axis=1)
        cos_in = np.abs((normal * dirs_W).sum(1)) / length
        footprint = t * length * pixel_rad / np.maximum(cos_in, 0.25)  # stretched on grazing surfaces, at most 4x
    return shade(scene, p, obj, normal, footprint), t  # rays have z = 1 in C, so t is the z-depth


def render_radiance(scene: Scene, T_WC: np.ndarray, K: np.ndarray, size: tuple[int, int],
                    supersample: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Brightness (h,w) in [0, 1], box-filtered over supersample^2 rays per pixel, and float32 z-depth (h,w) at
    pixel centres."""
    w, h = size
    s = supersample
    v, u = np.mgrid[0:h * s, 0:w * s]
    uu = (u + 0.5) / s - 0.5
    vv = (v + 0.5) / s - 0.5
    Ki = np.linalg.inv(K)
    rays = np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)], 1) @ Ki.T
    img, depth = render_rays(scene, T_WC, rays, 1.0 / (float(K[0, 0]) * s))
    img = img.reshape(h, s, w, s).mean(axis=(1, 3))
    if s > 1:  # depth at the pixel centres: the ray cast alone (rays with z = 1 in C: t is the z-depth)
        v, u = np.mgrid[0:h, 0:w]
        centres = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], 1).astype(float) @ Ki.T
        depth = raycast(scene, T_WC[:3, 3], centres @ T_WC[:3, :3].T)[0]
    return img, depth.reshape(h, w).astype(np.float32)


def render_pinhole(scene: Scene, T_WC: np.ndarray, K: np.ndarray, size: tuple[int, int], supersample: int = 2,
                   noise_std: float = 2.0, rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """uint8 image (h,w) (``render_radiance`` plus Gaussian noise [grey levels]) and float32 z-depth (h,w)."""
    img, depth = render_radiance(scene, T_WC, K, size, supersample)
    if rng is not None and noise_std > 0:
        img = img * 255.0 + rng.normal(0, noise_std, img.shape)
    else:
        img = img * 255.0
    return np.clip(img, 0, 255).astype(np.uint8), depth


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
