"""Exact depth images of a triangle mesh by ray casting (open3d): a fixture of the mapping and o2p tests, which the
mapping benchmarks borrow (``python -m tools bench mapping`` from a checkout).

:func:`room_scene` builds a small closed room with a box and a sphere in it; :func:`render_depth`
returns the z-depth (NaN where no hit) seen by a pinhole camera at ``T_WC`` (OpenCV axes).
"""

from __future__ import annotations

import numpy as np
import open3d as o3d


def room_scene(size=(6.0, 5.0, 3.0)) -> o3d.geometry.TriangleMesh:
    """A room [0, size] with inward walls, a 1 m box on the floor and a 0.5 m-radius sphere."""
    sx, sy, sz = size
    room = o3d.geometry.TriangleMesh.create_box(sx, sy, sz)
    room.triangles = o3d.utility.Vector3iVector(np.asarray(room.triangles)[:, ::-1])  # face inwards
    box = o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0)
    box.translate((sx * 0.6, sy * 0.55, 0.0))
    ball = o3d.geometry.TriangleMesh.create_sphere(0.5, resolution=40)
    ball.translate((sx * 0.3, sy * 0.7, 1.2))
    mesh = room + box + ball
    mesh.compute_vertex_normals()
    return mesh


def intrinsics(width: int = 512, height: int = 384, fov_x_deg: float = 80.0) -> np.ndarray:
    f = 0.5 * width / np.tan(np.radians(fov_x_deg) / 2)
    return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])


class DepthRenderer:
    """Ray-casting scene of one mesh."""

    def __init__(self, mesh: o3d.geometry.TriangleMesh) -> None:
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))

    def render(self, K: np.ndarray, width: int, height: int, T_WC: np.ndarray) -> np.ndarray:
        """z-depth (H, W) float32 [m] along the optical axis; NaN where the ray hits nothing."""
        u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
        d_C = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
        d_W = d_C @ T_WC[:3, :3].T
        o_W = np.broadcast_to(T_WC[:3, 3], d_W.shape)
        rays = np.concatenate([o_W, d_W], axis=-1).astype(np.float32)
        t = self.scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()  # in units of |d_C| with d_C.z = 1
        t[~np.isfinite(t)] = np.nan
        return t.astype(np.float32)


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """T_WC of a camera at ``eye`` looking at ``target`` (OpenCV axes: z forward, y down)."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, z])
    T[:3, 3] = eye
    return T
