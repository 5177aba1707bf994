"""Tiny ray-cast renderer for frontend tests: a camera rig inside a textured box room.

Each wall of the axis-aligned box carries the same smooth random texture at a different offset; a pixel's
ray is intersected with the walls (the nearest hit from inside the box) and the texture is sampled
bilinearly. :func:`raycast` gives the exact 3D point seen at any pixel (ground truth for tracks).
"""

from __future__ import annotations

import cv2
import numpy as np

from shared.camera import CameraCalib, CameraModel
from shared.geometry import make_T, so3_exp

TEXEL_M = 0.01


def texture(seed: int = 0, size: int = 1024) -> np.ndarray:
    """Smooth random texture with blobs at two scales, float32 in [0, 255]."""
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.random((size, size)).astype(np.float32), (0, 0), 2.0, borderType=cv2.BORDER_REFLECT)
    t2 = cv2.GaussianBlur(rng.random((size, size)).astype(np.float32), (0, 0), 8.0, borderType=cv2.BORDER_REFLECT)
    t = (t - t.mean()) / t.std() + 0.7 * (t2 - t2.mean()) / t2.std()
    return np.clip(128 + 45 * t, 0, 255).astype(np.float32)


class BoxRoom:
    """Axis-aligned box [lo, hi] (m) with textured walls."""

    def __init__(self, lo=(-5.0, -4.0, -1.5), hi=(6.0, 4.0, 2.5), seed: int = 0) -> None:
        self.lo, self.hi = np.array(lo, float), np.array(hi, float)
        self.tex = texture(seed)

    def hit(self, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest wall hit (N,3) of rays from ``origin`` (inside) along ``dirs`` (N,3), and the wall axis (N,)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            t_hi = (self.hi[None] - origin[None]) / dirs
            t_lo = (self.lo[None] - origin[None]) / dirs
        t = np.where(dirs > 0, t_hi, t_lo)
        t = np.where(np.isfinite(t) & (t > 0), t, np.inf)
        axis = np.argmin(t, axis=1)
        tmin = t[np.arange(len(t)), axis]
        return origin[None] + tmin[:, None] * dirs, axis

    def texcoords(self, p: np.ndarray, axis: np.ndarray) -> np.ndarray:
        """Texture pixel coordinates (N,2) of wall points p (N,3) on walls of axis (N,); each wall its own offset."""
        other = np.array([[1, 2], [0, 2], [0, 1]])[axis]
        side = (p[np.arange(len(p)), axis] > 0)[:, None]
        return np.take_along_axis(p, other, axis=1) / TEXEL_M + 173.0 * axis[:, None] + 311.0 * side

    def shade(self, p: np.ndarray, axis: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """Texture values (shape) at wall points p (N,3), N = prod(shape), sampled bilinearly (wrapping)."""
        n = self.tex.shape[0]
        uv = np.mod(self.texcoords(p, axis), n).astype(np.float32)
        return cv2.remap(self.tex, uv[:, 0].reshape(shape), uv[:, 1].reshape(shape), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_WRAP)


_RAYS: dict = {}


def render(room: BoxRoom, calib: CameraCalib, T_WS: np.ndarray) -> np.ndarray:
    """Grayscale image (H,W) uint8 of the room seen by ``calib`` on the body at ``T_WS``."""
    cam = calib.camera
    key = (id(calib.camera), cam.width, cam.height)
    if key not in _RAYS:  # unprojection of every pixel, once per camera
        _RAYS[key] = (calib.camera, cam.unproject(cam.pixel_grid()))
    T_WC = T_WS @ calib.T_SC
    rays = _RAYS[key][1] @ T_WC[:3, :3].T
    p, axis = room.hit(T_WC[:3, 3], rays)
    img = room.shade(p, axis, (cam.height, cam.width))
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def raycast(room: BoxRoom, calib: CameraCalib, T_WS: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Exact world point (N,3) seen at distorted pixels ``uv`` (N,2)."""
    T_WC = T_WS @ calib.T_SC
    rays = calib.camera.unproject(np.asarray(uv, float)) @ T_WC[:3, :3].T
    return room.hit(T_WC[:3, 3], rays)[0]


def project(calib: CameraCalib, T_WS: np.ndarray, p_W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    T_CW = np.linalg.inv(T_WS @ calib.T_SC)
    return calib.camera.project(p_W @ T_CW[:3, :3].T + T_CW[:3, 3])


def small_camera(dist=(-0.28, 0.07, 0.0, 0.0)) -> CameraModel:
    """EuRoC-like camera at half resolution (376x240) with radial-tangential distortion."""
    return CameraModel(376, 240, 230.0, 229.0, 190.0, 128.0, "radtan", dist)


def rig(yaws_deg=(0.0, 0.0), offsets=((0.0, 0.0, 0.0), (0.11, 0.0, 0.0))) -> list[CameraCalib]:
    """Cameras looking along +x of the body (OpenCV axes), each turned by a yaw about the body z axis."""
    R_S_C0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # C z -> S x, C x -> S -y
    out = []
    for k, (yaw, off) in enumerate(zip(yaws_deg, offsets)):
        R = so3_exp(np.array([0.0, 0.0, np.deg2rad(yaw)])) @ R_S_C0
        t = R_S_C0 @ np.asarray(off, float)
        out.append(CameraCalib(f"cam{k}", small_camera(), make_T(R, t), 20.0))
    return out


def body_pose(t: float, speed=0.4, yaw_rate=0.25) -> np.ndarray:
    """Body moving along x with a gentle yaw and bobbing, starting at the origin."""
    R = so3_exp(np.array([0.03 * np.sin(2 * t), 0.02 * np.sin(1.3 * t), yaw_rate * t]))
    return make_T(R, np.array([speed * t, 0.3 * np.sin(0.7 * t), 0.1 * np.sin(1.1 * t)]))


def relative_rotation(T0: np.ndarray, T1: np.ndarray) -> np.ndarray:
    """R_S0S1 (what the gyro integration gives)."""
    return T0[:3, :3].T @ T1[:3, :3]
