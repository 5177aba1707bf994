"""Projective integration of one depth image with per-pixel sigma into a block store (eq. 3-4).

Two passes, both compiled with numba:

1. *Block selection*: every block of the frustum's bounding box is projected into min/max depth
   pyramids of the image. A block whose whole footprint lies more than 3 sigma in front of the
   nearest depth is *clear* (free space: updated as a whole while it is coarse); a block entirely
   behind the farthest depth plus tau, outside the image or in front of nothing measured is left
   alone (unknown stays unknown); the rest are *mixed* (near a surface).
2. *Voxel update*: mixed blocks (and clear blocks that already have voxels) are refined and every
   voxel is projected into the image (nearest pixel), d_r is taken along the ray and eq. 3 + eq. 4
   are applied.
"""

from __future__ import annotations

import dataclasses
import warnings

import numba as nb
import numpy as np

from shared.occupancy.blocks import BlockStore, pack_keys
from services.mapping.config import SensorModelConfig

# the TBB layer numba finds here is too old; it falls back to another threading layer (harmless)
warnings.filterwarnings("ignore", message=".*TBB threading layer.*")

CLEAR, MIXED = 1, 2
_LEVELS = 9  # pyramid levels: cells of 1 .. 256 pixels
_WINDOW = 4  # a block's footprint is tested on the pyramid level whose cells are >= 1/_WINDOW of its diameter
_FIRST_LEVEL = 2  # finer levels are not built: a block at 6 m spans > 16 px; a coarser cell is only conservative


@dataclasses.dataclass(frozen=True)
class IntegrationResult:
    updated_slots: np.ndarray  # slots of blocks whose values changed
    n_clear: int  # blocks carved as a whole
    n_voxel_blocks: int  # blocks updated voxel by voxel
    n_pixels: int  # usable depth pixels
    n_carve_only: int = 0  # of those, pixels that only freed space (too uncertain for a surface)


def _pyramids(depth: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per-level min depth, max depth, max sigma, valid-pixel count and in-image pixel count, flattened
    level after level, and the (offset, rows, cols) of each level (level l has cells of 2^l pixels)."""
    c = 1 << (_LEVELS - 1)
    H, W = depth.shape
    Hp, Wp = -(-H // c) * c, -(-W // c) * c
    meta = np.zeros((_LEVELS - _FIRST_LEVEL, 3), np.int64)
    off = 0
    for i, level in enumerate(range(_FIRST_LEVEL, _LEVELS)):
        h, w = Hp >> level, Wp >> level
        meta[i] = off, h, w
        off += h * w
    out = [np.empty(off, np.float32) for _ in range(5)]
    _fill_pyramids(np.ascontiguousarray(depth, np.float32), np.ascontiguousarray(sigma, np.float32), meta, _FIRST_LEVEL, *out)
    return (*out, meta)


@nb.njit(cache=True)
def _fill_pyramids(depth, sigma, meta, first, dmin, dmax, smax, nval, npix):
    H, W = depth.shape
    n0, w0 = meta[0, 1] * meta[0, 2], meta[0, 2]
    for c in range(n0):
        dmin[c], dmax[c], smax[c], nval[c], npix[c] = np.inf, -np.inf, 0.0, 0.0, 0.0
    for y in range(H):
        row = (y >> first) * w0
        for x in range(W):
            c = row + (x >> first)
            npix[c] += 1.0
            d = depth[y, x]
            if d == d:
                dmin[c] = min(dmin[c], d)
                dmax[c] = max(dmax[c], d)
                smax[c] = max(smax[c], sigma[y, x])
                nval[c] += 1.0
    for level in range(1, meta.shape[0]):
        po, pw = meta[level - 1, 0], meta[level - 1, 2]
        off, h, w = meta[level, 0], meta[level, 1], meta[level, 2]
        for y in range(h):
            for x in range(w):
                c = off + y * w + x
                a = po + 2 * y * pw + 2 * x
                b = a + pw
                dmin[c] = min(min(dmin[a], dmin[a + 1]), min(dmin[b], dmin[b + 1]))
                dmax[c] = max(max(dmax[a], dmax[a + 1]), max(dmax[b], dmax[b + 1]))
                smax[c] = max(max(smax[a], smax[a + 1]), max(smax[b], smax[b + 1]))
                nval[c] = nval[a] + nval[a + 1] + nval[b] + nval[b + 1]
                npix[c] = npix[a] + npix[a + 1] + npix[b] + npix[b + 1]


@nb.njit(cache=True)
def _select_blocks(lo, hi, block_m, R, t, fx, fy, cx, cy, W, H, planes, dmin, dmax, smax, nval, npix, meta, first,
                   near, tau_max, min_valid_fraction, out_ijk, out_cls):
    r = 0.5 * np.sqrt(3.0) * block_m
    f = max(fx, fy)
    n = 0
    for i in range(lo[0], hi[0] + 1):
        for j in range(lo[1], hi[1] + 1):
            for k in range(lo[2], hi[2] + 1):
                px, py, pz = (i + 0.5) * block_m, (j + 0.5) * block_m, (k + 0.5) * block_m
                x = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
                y = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
                z = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
                if z + r < near:
                    continue
                inside = True
                for q in range(4):  # the sphere must reach inside every side plane of the frustum
                    if planes[q, 0] * x + planes[q, 1] * y + planes[q, 2] * z < -r:
                        inside = False
                        break
                if not inside:
                    continue
                if z - r < 2.0 * near:  # footprint unbounded: decide voxel by voxel
                    out_ijk[n, 0], out_ijk[n, 1], out_ijk[n, 2] = i, j, k
                    out_cls[n] = MIXED
                    n += 1
                    continue
                rad = f * r / (z - r)
                level = first
                while (1 << level) * _WINDOW < 2.0 * rad and level - first < meta.shape[0]:
                    level += 1
                if level - first >= meta.shape[0]:
                    out_ijk[n, 0], out_ijk[n, 1], out_ijk[n, 2] = i, j, k
                    out_cls[n] = MIXED
                    n += 1
                    continue
                u = fx * x / z + cx
                v = fy * y / z + cy
                if u + rad < -0.5 or u - rad > W - 0.5 or v + rad < -0.5 or v - rad > H - 0.5:
                    continue
                cell = float(1 << level)
                off, h, w = meta[level - first, 0], meta[level - first, 1], meta[level - first, 2]
                x0 = min(max(int(np.floor((u + 0.5 - rad) / cell)), 0), w - 1)
                x1 = min(max(int(np.floor((u + 0.5 + rad) / cell)), 0), w - 1)
                y0 = min(max(int(np.floor((v + 0.5 - rad) / cell)), 0), h - 1)
                y1 = min(max(int(np.floor((v + 0.5 + rad) / cell)), 0), h - 1)
                mn, mx, sm, nv, npx = np.inf, -np.inf, 0.0, 0.0, 0.0
                for yy in range(y0, y1 + 1):
                    for xx in range(x0, x1 + 1):
                        c = off + yy * w + xx
                        mn = min(mn, dmin[c])
                        mx = max(mx, dmax[c])
                        sm = max(sm, smax[c])
                        nv += nval[c]
                        npx += npix[c]
                if nv == 0.0:
                    continue
                if z + r < mn - 3.0 * sm and nv >= min_valid_fraction * npx:
                    cls = CLEAR
                elif z - r > mx + tau_max:
                    continue
                else:
                    cls = MIXED
                out_ijk[n, 0], out_ijk[n, 1], out_ijk[n, 2] = i, j, k
                out_cls[n] = cls
                n += 1
    return n


# Fast-math without 'nnan'/'ninf': pixels without depth are NaN, and under 'nnan' the compiler may (and did) drop the
# `D > 0` test that skips them: each such pixel then carved its whole ray free, through and behind the surfaces.
_FAST = {"contract", "arcp", "reassoc", "nsz", "afn"}


@nb.njit(parallel=True, fastmath=_FAST, cache=True)
def _update_voxels(bijk, rows, Lv, wv, R, t, fx, fy, cx, cy, depth, sigma, carve_only, vs, l_min, w_max,
                   tau_k, tau_sigma_k, tau_min, tau_max, near, changed):
    H, W = depth.shape
    B = Lv.shape[1]
    for b in nb.prange(bijk.shape[0]):
        row = rows[b]
        any_change = False
        for a in range(B):
            px = (bijk[b, 0] * B + a + 0.5) * vs
            for c in range(B):
                py = (bijk[b, 1] * B + c + 0.5) * vs
                for e in range(B):
                    pz = (bijk[b, 2] * B + e + 0.5) * vs
                    z = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
                    if z < near:
                        continue
                    x = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
                    y = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
                    ui = int(np.floor(fx * x / z + cx + 0.5))
                    vi = int(np.floor(fy * y / z + cy + 0.5))
                    if ui < 0 or ui >= W or vi < 0 or vi >= H:
                        continue
                    D = depth[vi, ui]
                    if not (D > 0.0):
                        continue
                    scale = np.sqrt(x * x + y * y + z * z) / z
                    d_r = (z - D) * scale
                    three_s = 3.0 * sigma[vi, ui] * scale
                    tau = min(max(max(tau_k * D, tau_sigma_k * sigma[vi, ui]) * scale, tau_min), tau_max)
                    if d_r < -three_s:
                        l = l_min
                    elif carve_only[vi, ui]:  # too unsure to place a surface: only the space well in front is free
                        continue
                    elif d_r < 0.5 * tau:
                        l = -l_min * d_r / three_s
                    elif d_r < tau:
                        l = -l_min * 0.5 * tau / three_s
                    else:
                        continue
                    w = wv[row, a, c, e]
                    Lv[row, a, c, e] = (Lv[row, a, c, e] * w + l) / (w + 1.0)
                    if w < w_max:
                        wv[row, a, c, e] = w + 1
                    any_change = True
        changed[b] = any_change


def _frustum_planes(K: np.ndarray, W: int, H: int) -> np.ndarray:
    """Unit inward normals (4, 3) of the side planes of the image frustum (camera frame)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    u0, u1, v0, v1 = -0.5, W - 0.5, -0.5, H - 0.5
    n = np.array([[fx, 0, cx - u0], [-fx, 0, u1 - cx], [0, fy, cy - v0], [0, -fy, v1 - cy]], float)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def integrate(store: BlockStore, depth: np.ndarray, sigma: np.ndarray, K: np.ndarray, T_MC: np.ndarray,
              cfg: SensorModelConfig, carve_only: np.ndarray | None = None) -> IntegrationResult:
    """Integrate depth/sigma (already through :func:`prepare_depth`: NaN = unusable) seen from
    camera pose ``T_MC`` (camera in the field frame) with pinhole ``K``. Pixels where ``carve_only`` (H, W) is
    true only free the space more than 3 sigma in front of their depth
    (shared/occupancy/uncertain_pixels.py)."""
    H, W = depth.shape
    n_pix = int(np.isfinite(depth).sum())
    carve = np.zeros((H, W), np.bool_) if carve_only is None else np.ascontiguousarray(carve_only, np.bool_)
    n_carve = int(np.count_nonzero(carve & np.isfinite(depth))) if carve_only is not None else 0
    empty = IntegrationResult(np.empty(0, np.int64), 0, 0, n_pix, n_carve)
    if n_pix == 0:
        return empty
    T_CM = np.linalg.inv(T_MC)
    R, t = np.ascontiguousarray(T_CM[:3, :3]), np.ascontiguousarray(T_CM[:3, 3])
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    far = float(np.nanmax(depth)) + cfg.tau_max_m
    uv = np.array([[-0.5, -0.5], [W - 0.5, -0.5], [-0.5, H - 0.5], [W - 0.5, H - 0.5]])
    rays = np.column_stack([(uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy, np.ones(4)])
    corners_M = np.vstack([T_MC[:3, 3], (rays * far) @ T_MC[:3, :3].T + T_MC[:3, 3]])
    bm = store.block_m
    lo = np.floor(corners_M.min(axis=0) / bm).astype(np.int64) - 1
    hi = np.floor(corners_M.max(axis=0) / bm).astype(np.int64) + 1
    n_max = int(np.prod(hi - lo + 1))
    out_ijk = np.empty((n_max, 3), np.int64)
    out_cls = np.empty(n_max, np.int8)
    dmin, dmax, smax, nval, npix, meta = _pyramids(depth, sigma)
    n = _select_blocks(lo, hi, bm, R, t, fx, fy, cx, cy, W, H, _frustum_planes(K, W, H), dmin, dmax, smax, nval,
                       npix, meta, _FIRST_LEVEL, cfg.near_m, cfg.tau_max_m, cfg.min_valid_fraction, out_ijk, out_cls)
    if n == 0:
        return empty
    ijk, cls = out_ijk[:n], out_cls[:n]
    slots = store.insert(pack_keys(ijk))
    was_unknown = (store.vox_slot[slots] < 0) & (store.coarse_w[slots] == 0)  # new, or allocated but never seen
    coarse_clear = (cls == CLEAR) & (store.vox_slot[slots] < 0)
    sc = slots[coarse_clear]
    w = store.coarse_w[sc].astype(np.float32)
    store.coarse_L[sc] = (store.coarse_L[sc] * w + np.float32(cfg.l_min)) / (w + 1.0)
    store.coarse_w[sc] = np.minimum(w + 1, cfg.w_max).astype(np.uint16)
    fine = ~coarse_clear
    sv = slots[fine]
    store.refine(sv)
    changed = np.zeros(len(sv), bool)
    _update_voxels(np.ascontiguousarray(ijk[fine]), store.vox_slot[sv].astype(np.int64), store.Lv, store.wv, R, t,
                   fx, fy, cx, cy, depth, sigma, carve, store.voxel_size, float(cfg.l_min), int(cfg.w_max), cfg.tau_k,
                   cfg.tau_sigma_k, cfg.tau_min_m, cfg.tau_max_m, cfg.near_m, changed)
    store.unrefine(sv[~changed & was_unknown[fine]])  # refined for nothing: back to unknown coarse
    return IntegrationResult(np.concatenate([sc, sv[changed]]), int(len(sc)), int(len(sv)), n_pix, n_carve)


def warm_up(cfg: SensorModelConfig | None = None) -> None:
    """Compile (or load from cache) the numba kernels on a tiny frame, so that the first real frame (and the first
    mesh's colours: the field queries of shared/occupancy/query.py) does not pay for it."""
    from shared.occupancy.query import warm_up as warm_up_queries

    cfg = cfg or SensorModelConfig()
    K = np.array([[20.0, 0.0, 15.5], [0.0, 20.0, 11.5], [0.0, 0.0, 1.0]])
    depth = np.full((24, 32), 1.0, np.float32)
    store = BlockStore(cfg.voxel_size_m)
    integrate(store, depth, np.full_like(depth, cfg.sigma_min_m), K, np.eye(4), cfg)
    warm_up_queries()
