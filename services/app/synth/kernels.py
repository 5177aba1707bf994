"""Compiled (numba, parallel) per-ray kernels of the renderer: ray construction and texturing.

They fuse what would otherwise be a dozen full-image numpy temporaries into one pass over the rays;
the numpy reference of :func:`shade_rays` is ``Renderer._sample_texture`` (kept for tests).
"""
from __future__ import annotations

import math

import numba
import numpy as np

INVALID = 0xFFFFFFFF


@numba.njit(parallel=True, cache=True)
def build_rays(rays_C, R, t, out):
    """out (N, 6) float32 = [t, R @ ray] for rays_C (N, 3) float32 given in C."""
    for i in numba.prange(rays_C.shape[0]):
        x, y, z = rays_C[i, 0], rays_C[i, 1], rays_C[i, 2]
        out[i, 0], out[i, 1], out[i, 2] = t[0], t[1], t[2]
        out[i, 3] = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z
        out[i, 4] = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z
        out[i, 5] = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z


@numba.njit(inline="always")
def _bilinear(flat, off, w, h, x, y):
    x = min(max(x, 0.0), w - 1.0)
    y = min(max(y, 0.0), h - 1.0)
    x0, y0 = int(x), int(y)
    x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
    fx, fy = x - x0, y - y0
    a = flat[off + y0 * w + x0] * (1.0 - fx) + flat[off + y0 * w + x1] * fx
    b = flat[off + y1 * w + x0] * (1.0 - fx) + flat[off + y1 * w + x1] * fx
    return a * (1.0 - fy) + b * fy


@numba.njit(parallel=True, cache=True)
def shade_rays(ids, bary, t_hit, dirs_W, tri_uv, tri_shade, normals, mip_flat, mip_off, mip_w, mip_h,
               texels_per_px, out):
    """out (N,) float32: albedo (0..1) x shade of each ray's hit, with trilinear mip filtering.

    The pixel footprint on the surface is depth x ``texels_per_px`` (texels per metre / focal length)
    stretched by 1/sqrt(cos incidence); the two mip levels bracketing it are blended."""
    n_levels = mip_off.shape[0]
    for i in numba.prange(ids.shape[0]):
        pid = ids[i]
        if pid == INVALID or not math.isfinite(t_hit[i]):
            out[i] = 0.0
            continue
        u, v = bary[i, 0], bary[i, 1]
        w0 = 1.0 - u - v
        tx = w0 * tri_uv[pid, 0, 0] + u * tri_uv[pid, 1, 0] + v * tri_uv[pid, 2, 0]
        ty = w0 * tri_uv[pid, 0, 1] + u * tri_uv[pid, 1, 1] + v * tri_uv[pid, 2, 1]
        dx, dy, dz = dirs_W[i, 3], dirs_W[i, 4], dirs_W[i, 5]
        norm = math.sqrt(dx * dx + dy * dy + dz * dz)
        cos = abs(dx * normals[pid, 0] + dy * normals[pid, 1] + dz * normals[pid, 2]) / norm
        fp = t_hit[i] * texels_per_px / math.sqrt(max(cos, 0.05))
        level = min(max(math.log2(max(fp, 1e-6)), 0.0), n_levels - 1.0)
        l0 = int(level)
        l1 = min(l0 + 1, n_levels - 1)
        f = level - l0
        s0, s1 = 0.5 ** l0, 0.5 ** l1  # cv2.pyrDown: texel j of level k is centred on texel 2^k j of level 0
        a = _bilinear(mip_flat, mip_off[l0], mip_w[l0], mip_h[l0], tx * s0, ty * s0)
        val = a
        if f > 0.0:
            b = _bilinear(mip_flat, mip_off[l1], mip_w[l1], mip_h[l1], tx * s1, ty * s1)
            val = (1.0 - f) * a + f * b
        out[i] = val * tri_shade[pid] / 255.0


def flatten_mips(mips: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A pyramid as one flat uint8 buffer + per-level offsets, widths, heights (int64)."""
    flat = np.concatenate([m.ravel() for m in mips])
    sizes = np.array([m.size for m in mips], np.int64)
    off = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
    return (flat, off, np.array([m.shape[1] for m in mips], np.int64), np.array([m.shape[0] for m in mips], np.int64))
