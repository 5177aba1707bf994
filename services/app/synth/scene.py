"""Procedural textured indoor scenes at the scale of EuRoC's Vicon room and Machine Hall.

A scene is a room (floor, walls, ceiling) sized from the ground-truth extents of the site's real
trajectories plus a margin, filled with clutter (boxes, tables on legs, cylinders, shelves) that keeps
at least ``clearance_m`` from every ground-truth position. Every planar patch (at most
``tile_px / texels_per_m`` metres on a side) gets its own tile of a texture atlas, so textures never
repeat. The triangle mesh is exact: it is what the renderer ray-casts and what mapping is scored against.

Per triangle: atlas pixel coordinates of its 3 corners (``tri_uv``), a Lambertian shading factor
(``tri_shade``). Deterministic in (name, seed): every replica of a site is rendered in the same scene, whatever
its own trajectory, so that a map made in one replica can be found again from another (``sigmaslam eval
relocalise``). The atlas is packed in shelves, so a patch one texel wider moves the texture of every later patch: the
room's size must not depend on a replica's trajectory. A replica's trajectory inside the site's room only removes the
objects it would pass through (their atlas tiles stay allocated, so every other patch keeps its texture); one that
leaves the room gets a room of its own.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.app.synth.textures import make_atlas

SITES = {"vicon": ("V1_02", "V2_01"), "machinehall": ("MH_04",)}
# name -> (site, texture style, object count, object size scale, light direction seed offset)
SCENES = {
    "vicon-a": ("vicon", "photo", 45, 1.0, 0),
    "vicon-b": ("vicon", "pattern", 60, 0.8, 1),
    "machinehall-a": ("machinehall", "photo", 110, 2.0, 2),
    "machinehall-b": ("machinehall", "pattern", 140, 1.6, 3),
}
SITE_MARGIN_M = {"vicon": 1.8, "machinehall": 3.0}
SITE_TEXELS_PER_M = {"vicon": 256.0, "machinehall": 128.0}


@dataclass
class Scene:
    name: str
    seed: int
    vertices: np.ndarray  # (V, 3) float64 [m] in W
    triangles: np.ndarray  # (F, 3) int32
    tri_uv: np.ndarray  # (F, 3, 2) float32 atlas pixel coordinates (x = column, y = row) of each corner
    tri_shade: np.ndarray  # (F,) float32 shading factor
    atlas: np.ndarray  # (H, W) uint8 albedo (255 = 1)
    room_min: np.ndarray  # (3,) [m]
    room_max: np.ndarray  # (3,) [m]
    texels_per_m: float = 256.0  # atlas texels per metre of surface

    @property
    def max_range_m(self) -> float:
        """Longest possible distance inside the room (its diagonal) [m]."""
        return float(np.linalg.norm(self.room_max - self.room_min))

    def save_ply(self, path: str | Path) -> Path:
        """Write the exact triangle mesh as binary PLY (float64 vertices, int32 faces)."""
        path = Path(path)
        v = np.ascontiguousarray(self.vertices, "<f8")
        f = np.empty(len(self.triangles), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
        f["n"], f["idx"] = 3, self.triangles
        header = (f"ply\nformat binary_little_endian 1.0\ncomment sigmaslam scene {self.name} seed {self.seed}\n"
                  f"element vertex {len(v)}\nproperty double x\nproperty double y\nproperty double z\n"
                  f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n")
        with open(path, "wb") as fh:
            fh.write(header.encode())
            fh.write(v.tobytes())
            fh.write(f.tobytes())
        return path


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a mesh written by :meth:`Scene.save_ply` (or any triangle PLY open3d reads): (vertices, triangles)."""
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.triangles) == 0:
        raise ValueError(f"{path}: no triangles")
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.triangles, np.int32)


class _Builder:
    """Collects textured quads, cut into patches of at most ``patch_m``, packed into atlas shelves."""

    def __init__(self, tile_px: int, texels_per_m: float, light_W: np.ndarray, atlas_width: int = 8192):
        self.tile_px, self.tpm, self.atlas_width = tile_px, texels_per_m, atlas_width
        self.patch_m = (tile_px - 2) / texels_per_m
        self.light = light_W / np.linalg.norm(light_W)
        self.verts: list[np.ndarray] = []
        self.uv: list[np.ndarray] = []  # (4, 2) atlas pixel coords
        self.shade: list[float] = []
        self.left_out: set[int] = set()  # quads allocated in the atlas but not part of the mesh (leave_out)
        self._x = self._y = self._row_h = 0

    def _alloc(self, w_m: float, h_m: float) -> np.ndarray:
        """Atlas pixel origin of a free (w_m x h_m) area, with a 1-texel gutter (shelf packing)."""
        w, h = int(np.ceil(w_m * self.tpm)) + 3, int(np.ceil(h_m * self.tpm)) + 3
        if self._x + w > self.atlas_width:
            self._x, self._y, self._row_h = 0, self._y + self._row_h, 0
        org = np.array([self._x + 1.0, self._y + 1.0])
        self._x += w
        self._row_h = max(self._row_h, h)
        return org

    def _shade(self, n: np.ndarray, albedo: float) -> float:
        return albedo * (0.55 + 0.45 * abs(float(n @ self.light)))

    def quad(self, origin, eu, ev, su: float, sv: float, albedo: float = 1.0) -> None:
        """Rectangle origin + a*eu + b*ev, a in [0, su], b in [0, sv] (eu, ev unit, orthogonal)."""
        origin, eu, ev = (np.asarray(x, float) for x in (origin, eu, ev))
        shade = self._shade(np.cross(eu, ev), albedo)
        nu, nv = max(1, int(np.ceil(su / self.patch_m - 1e-9))), max(1, int(np.ceil(sv / self.patch_m - 1e-9)))
        au, av = np.linspace(0, su, nu + 1), np.linspace(0, sv, nv + 1)
        for i in range(nu):
            for j in range(nv):
                a0, a1, b0, b1 = au[i], au[i + 1], av[j], av[j + 1]
                org = self._alloc(a1 - a0, b1 - b0)
                corners = [(a0, b0), (a1, b0), (a1, b1), (a0, b1)]
                self.verts.append(np.array([origin + a * eu + b * ev for a, b in corners]))
                self.uv.append(org + np.array([[a - a0, b - b0] for a, b in corners]) * self.tpm)
                self.shade.append(shade)

    def box(self, c, size, yaw: float = 0.0, albedo: float = 1.0, bottom: bool = False) -> None:
        """Box with centre of its bottom face at c, size (sx, sy, sz), rotated by yaw about z."""
        sx, sy, sz = size
        cy_, sy_ = np.cos(yaw), np.sin(yaw)
        ex, ey, ez = np.array([cy_, sy_, 0.0]), np.array([-sy_, cy_, 0.0]), np.array([0.0, 0.0, 1.0])
        p0 = np.asarray(c, float) - ex * sx / 2 - ey * sy / 2  # bottom corner
        self.quad(p0 + ez * sz, ex, ey, sx, sy, albedo)  # top
        if bottom:
            self.quad(p0 + ey * sy, ex, -ey, sx, sy, albedo)
        self.quad(p0, ex, ez, sx, sz, albedo)
        self.quad(p0 + ey * sy + ex * sx, -ex, ez, sx, sz, albedo)
        self.quad(p0 + ex * sx, ey, ez, sy, sz, albedo)
        self.quad(p0 + ey * sy, -ey, ez, sy, sz, albedo)

    def cylinder(self, c, radius: float, height: float, segments: int = 20, albedo: float = 1.0) -> None:
        """Upright cylinder (side as one continuous texture strip, top as a textured fan) standing at c."""
        c = np.asarray(c, float)
        ang = np.linspace(0, 2 * np.pi, segments + 1)
        ring = np.stack([np.cos(ang), np.sin(ang), 0 * ang], 1)
        pts = c + radius * ring
        seg = float(np.linalg.norm(pts[1] - pts[0]))
        per_strip = max(1, int(self.patch_m // seg))
        for k in range(segments):
            if k % per_strip == 0:
                nz = max(1, int(np.ceil(height / self.patch_m - 1e-9)))
                zs = np.linspace(0, height, nz + 1)
                orgs = [self._alloc(seg * min(per_strip, segments - k), zs[j + 1] - zs[j]) for j in range(nz)]
            u0 = (k % per_strip) * seg
            n = ring[k] + ring[k + 1]
            for j in range(nz):
                self.verts.append(np.array([pts[k] + [0, 0, zs[j]], pts[k + 1] + [0, 0, zs[j]],
                                            pts[k + 1] + [0, 0, zs[j + 1]], pts[k] + [0, 0, zs[j + 1]]]))
                self.uv.append(orgs[j] + np.array([[u0, 0], [u0 + seg, 0], [u0 + seg, zs[j + 1] - zs[j]],
                                                   [u0, zs[j + 1] - zs[j]]]) * self.tpm)
                self.shade.append(self._shade(n / np.linalg.norm(n), albedo))
        org = self._alloc(2 * radius, 2 * radius)
        top = c + [0, 0, height]
        for k in range(0, segments, 2):
            rim = ring[[k, k + 1, (k + 2) % segments]]
            self.verts.append(np.concatenate([top[None], top + radius * rim]))
            local = np.concatenate([[[0.0, 0.0]], rim[:, :2]]) * radius + radius
            self.uv.append(org + local * self.tpm)
            self.shade.append(self._shade(np.array([0.0, 0.0, 1.0]), albedo))

    def leave_out(self, first: int) -> None:
        """Leave the quads from index ``first`` on (the object just added) out of the mesh; their atlas areas stay
        taken, so the patches after them keep their textures."""
        self.left_out.update(range(first, len(self.verts)))

    def finish(self, name: str, seed: int, style: str, room_min, room_max, textures: bool = True) -> Scene:
        rows = int(np.ceil((self._y + self._row_h + 1) / self.tile_px))
        atlas = (make_atlas(rows, self.atlas_width // self.tile_px, self.tile_px, style, seed) if textures
                 else np.full((rows * self.tile_px, self.atlas_width), 128, np.uint8))
        kept = [i for i in range(len(self.verts)) if i not in self.left_out]
        q = np.stack([self.verts[i] for i in kept])  # (Q, 4, 3)
        nq = len(q)
        uv = np.stack([self.uv[i] for i in kept])  # (Q, 4, 2)
        base = (np.arange(nq) * 4)[:, None]
        tris = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]]).astype(np.int32)
        tri_uv = np.concatenate([uv[:, [0, 1, 2]], uv[:, [0, 2, 3]]]).astype(np.float32)
        shade_q = [self.shade[i] for i in kept]
        shade = np.concatenate([shade_q, shade_q]).astype(np.float32)
        return Scene(name, seed, q.reshape(-1, 3), tris, tri_uv, shade, atlas, np.asarray(room_min, float),
                     np.asarray(room_max, float), self.tpm)


def site_positions(site: str, extra: list[np.ndarray] | None = None) -> np.ndarray:
    """Ground-truth positions (N, 3) of all known trajectories of ``site`` (plus ``extra`` ones)."""
    pts = [_site_ground_truth(site)] + [np.asarray(e, float).reshape(-1, 3) for e in (extra or [])]
    return np.concatenate(pts)


@functools.lru_cache(maxsize=4)
def _site_ground_truth(site: str) -> np.ndarray:
    """The positions of the site's sequences (read once per process; read-only)."""
    from shared.euroc import read_euroc_csv
    from shared.paths import euroc_files

    pts = np.concatenate([read_euroc_csv(euroc_files(s)["groundtruth"]).p_WS for s in SITES[site]])
    pts.setflags(write=False)
    return pts


def _box_distance(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> float:
    """Smallest distance from points (N, 3) to the axis-aligned box [lo, hi]."""
    d = np.maximum(np.maximum(lo - points, points - hi), 0.0)
    return float(np.sqrt((d * d).sum(1)).min())


def build_scene(name: str, seed: int = 0, positions: np.ndarray | None = None, clearance_m: float = 0.5,
                tile_px: int = 256, extra_positions: np.ndarray | None = None, textures: bool = True) -> Scene:
    """Build scene ``name`` (see :data:`SCENES`) around the site's GT positions, or ``positions`` (N, 3)
    instead; ``extra_positions`` (the replica's own trajectory) are kept clear and inside the room too: inside the
    site's room they remove the objects closer than ``clearance_m`` and change nothing else (module doc); outside it
    the room and its objects are made around both. ``textures=False`` skips the texture atlas (uniform grey):
    geometry only, much faster."""
    if name not in SCENES:
        raise KeyError(f"unknown scene {name!r}; known: {', '.join(SCENES)}")
    site = SCENES[name][0]
    pts = _thin(site_positions(site) if positions is None else np.asarray(positions, float).reshape(-1, 3))
    extra = None if extra_positions is None else _thin(np.asarray(extra_positions, float).reshape(-1, 3))
    if extra is not None and not _inside(extra, *_room(site, pts)):
        pts, extra = _thin(np.concatenate([pts, extra])), None  # a room of its own around both
    return _furnish(name, seed, pts, clearance_m, tile_px, textures, keep_clear=extra)


def _thin(pts: np.ndarray) -> np.ndarray:
    """At most ~20 000 of ``pts`` (every k-th): enough for the room's extent and the objects' clearance."""
    return pts[:: max(1, len(pts) // 20000)]


def _room(site: str, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The room (lo, hi corners [m]) around positions ``pts`` of ``site``: a margin around them, the floor at z <= 0."""
    margin = SITE_MARGIN_M[site]
    lo, hi = pts.min(0) - margin, pts.max(0) + margin
    lo[2] = min(0.0, pts[:, 2].min() - 0.5)
    hi[2] = pts[:, 2].max() + (1.5 if site == "vicon" else 3.0)
    return lo, hi


def _inside(pts: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Whether every position lies in the room, with the site margin's worth of air to the walls left at half."""
    return bool(np.all(pts >= lo + 0.5) and np.all(pts <= hi - 0.5))


def _furnish(name: str, seed: int, pts: np.ndarray, clearance_m: float, tile_px: int, textures: bool,
             keep_clear: np.ndarray | None) -> Scene:
    """The room around ``pts`` with its objects placed clear of ``pts``; objects closer than ``clearance_m`` to
    ``keep_clear`` are left out afterwards, keeping the atlas layout (and so every other patch's texture)."""
    site, style, n_obj, scale, light_off = SCENES[name]
    rng = np.random.default_rng([seed, light_off])
    lo, hi = _room(site, pts)
    light = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(1.0, 2.0)])
    b = _Builder(tile_px, SITE_TEXELS_PER_M[site], light)
    size = hi - lo
    ex, ey, ez = np.eye(3)
    b.quad(lo, ex, ey, size[0], size[1], 0.9)  # floor
    b.quad([lo[0], lo[1], hi[2]], ex, ey, size[0], size[1], 0.8)  # ceiling
    b.quad(lo, ex, ez, size[0], size[2])
    b.quad([lo[0], hi[1], lo[2]], ex, ez, size[0], size[2])
    b.quad(lo, ey, ez, size[1], size[2])
    b.quad([hi[0], lo[1], lo[2]], ey, ez, size[1], size[2])
    placed, tries = 0, 0
    while placed < n_obj and tries < 50 * n_obj:
        tries += 1
        kind = rng.choice(["box", "box", "table", "cylinder", "shelf", "stack"])
        yaw = rng.uniform(0, np.pi) if rng.random() < 0.6 else 0.0
        if kind == "box":
            sx, sy, sz = rng.uniform(0.3, 1.2, 3) * scale
        elif kind == "stack":
            sx, sy = rng.uniform(0.4, 0.9, 2) * scale
            sz = rng.uniform(1.0, 2.0) * scale
        elif kind == "table":
            sx, sy, sz = rng.uniform(0.6, 1.4) * scale, rng.uniform(0.5, 1.0) * scale, rng.uniform(0.6, 1.1)
        elif kind == "cylinder":
            sx = sy = 2 * rng.uniform(0.1, 0.4) * scale
            sz = rng.uniform(0.5, size[2]) if rng.random() < 0.7 else size[2]
        else:
            sx, sy, sz = rng.uniform(0.8, 2.0) * scale, rng.uniform(0.3, 0.5) * scale, rng.uniform(1.2, 2.2) * scale
        sz = min(sz, size[2])
        r = 0.5 * np.hypot(sx, sy)
        c = np.array([rng.uniform(lo[0] + r, hi[0] - r), rng.uniform(lo[1] + r, hi[1] - r), lo[2]])
        if c[0] - r < lo[0] or c[1] - r < lo[1]:
            continue
        top = sz * (1.3 if kind == "stack" else 1.0)  # a stack carries a second box of 0.3 sz
        box_lo, box_hi = c - [r, r, 0], c + [r, r, top]
        if _box_distance(pts, box_lo, box_hi) < clearance_m:
            continue
        alb = rng.uniform(0.7, 1.2)
        first = len(b.verts)
        if kind in ("box", "stack"):
            b.box(c, (sx, sy, sz), yaw, alb)
            if kind == "stack" and c[2] + 1.3 * sz < hi[2]:
                b.box(c + [0, 0, sz], (0.7 * sx, 0.7 * sy, 0.3 * sz), yaw + 0.3, alb)
        elif kind == "table":
            cy_, sy_ = np.cos(yaw), np.sin(yaw)
            R = np.array([[cy_, -sy_], [sy_, cy_]])
            for dx, dy in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                off = R @ np.array([dx * (sx / 2 - 0.05), dy * (sy / 2 - 0.05)])
                b.box(c + [off[0], off[1], 0], (0.05, 0.05, sz - 0.04), yaw, alb)
            b.box(c + [0, 0, sz - 0.04], (sx, sy, 0.04), yaw, alb, bottom=True)
        elif kind == "cylinder":
            b.cylinder(c, sx / 2, sz, albedo=alb)
        else:  # shelf: two side panels and boards
            cy_, sy_ = np.cos(yaw), np.sin(yaw)
            exy = np.array([cy_, sy_, 0.0])
            for s in (-1, 1):
                b.box(c + exy * s * (sx / 2 - 0.02), (0.03, sy, sz), yaw, alb)
            for z in np.linspace(0.05, sz - 0.03, int(rng.integers(3, 6))):
                b.box(c + [0, 0, z], (sx - 0.07, sy, 0.03), yaw, alb * 0.9, bottom=True)
        placed += 1
        if keep_clear is not None and _box_distance(keep_clear, box_lo, box_hi) < clearance_m:
            b.leave_out(first)
    return b.finish(name, seed, style, lo, hi, textures)
