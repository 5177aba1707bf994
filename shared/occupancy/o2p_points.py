"""Depth points for occupancy-to-point factors (paper eq. 6, sec. IV-C): the lowest-sigma pixels of a depth
frame, spread over the image, and a per-submap pool of the fused-depth points integrated into it (the
points of its map-to-map factor), kept in the submap frame M.

The pool keeps at most ``max_points`` points: each integrated frame contributes its lowest-sigma pixels of
a 4x subsampled image (cheap: ~12k pixels at 512x384), and when the pool overflows it keeps the lowest
sigma per ``cell_m`` cube first, so that the points stay spread over the submap, then the lowest sigma.
"""

from __future__ import annotations

import numpy as np

from shared.occupancy.blocks import pack_keys


def select_depth_points(depth: np.ndarray, sigma: np.ndarray, K: np.ndarray, max_points: int,
                        cell_px: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Back-projected camera-frame points (N, 3) and sigmas (N,) of at most ``max_points`` valid pixels
    with the lowest sigma, at most one per ``cell_px`` square (0: chosen so there are ~4 max_points cells)."""
    depth = np.asarray(depth, np.float32)
    sigma = np.asarray(sigma, np.float32)
    if depth.ndim != 2 or depth.shape != sigma.shape:
        raise ValueError(f"depth {depth.shape} and sigma {sigma.shape} must be equal 2-D arrays")
    H, W = depth.shape
    cell = cell_px or max(1, int(np.sqrt(H * W / (4.0 * max_points))))
    # the image as cells of cell x cell pixels (padded with invalid ones), one row per cell in raster order; the
    # lowest valid sigma of each cell is its candidate (the first in the cell's raster order among equals)
    Hc, Wc = -(-H // cell), -(-W // cell)
    key = np.full((Hc * cell, Wc * cell), np.inf, np.float32)
    key[:H, :W] = np.where(np.isfinite(depth) & (depth > 0) & np.isfinite(sigma) & (sigma > 0), sigma, np.inf)
    cells = key.reshape(Hc, cell, Wc, cell).transpose(0, 2, 1, 3).reshape(Hc * Wc, cell * cell)
    best = np.argmin(cells, axis=1)
    s = cells[np.arange(len(best)), best]
    c = np.flatnonzero(np.isfinite(s))  # cells with a valid pixel
    if len(c) == 0:
        return np.empty((0, 3)), np.empty(0)
    best, s = best[c], s[c]
    v, u = (c // Wc) * cell + best // cell, (c % Wc) * cell + best % cell
    # lowest sigma first; ties (e.g. a constant heuristic sigma) broken by a fixed shuffle so the points spread
    tie = np.random.default_rng(0).permutation(len(c))
    keep = np.lexsort((tie, s))[:max_points]
    v, u = v[keep], u[keep]
    z = depth[v, u].astype(np.float64)
    p = np.column_stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])
    return p, s[keep].astype(np.float64)


class SubmapPointPool:
    """Lowest-sigma depth points of each submap, in its frame M (N, 3) [m] with sigmas (N,) [m]."""

    def __init__(self, max_points: int = 1000, per_frame: int = 300, cell_m: float = 0.1, subsample: int = 4) -> None:
        if min(max_points, per_frame, subsample) < 1 or cell_m <= 0:
            raise ValueError("max_points, per_frame, subsample >= 1 and cell_m > 0 are required")
        self.max_points, self.per_frame, self.cell_m, self.subsample = max_points, per_frame, cell_m, subsample
        self.pools: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def add(self, submap_id: int, depth: np.ndarray, sigma: np.ndarray, K: np.ndarray, T_MC: np.ndarray) -> int:
        """Pool one integrated frame (raw depth/sigma, NaN invalid); returns the pool size."""
        k = self.subsample
        o = (k - 1) // 2  # pixel k i + o of the full image is pixel i of the subsampled one
        Ks = np.asarray(K, float).copy()
        Ks[:2] /= k
        Ks[:2, 2] = (np.asarray(K, float)[:2, 2] - o) / k
        p_C, s = select_depth_points(np.asarray(depth)[o::k, o::k], np.asarray(sigma)[o::k, o::k], Ks, self.per_frame)
        p_M = p_C @ np.asarray(T_MC, float)[:3, :3].T + np.asarray(T_MC, float)[:3, 3]
        old_p, old_s = self.pools.get(submap_id, (np.empty((0, 3)), np.empty(0)))
        p, s = np.vstack([old_p, p_M]), np.concatenate([old_s, s])
        if len(p) > self.max_points:
            cid = pack_keys(np.floor(p / self.cell_m).astype(np.int64))
            order = np.lexsort((s, cid))
            first = order[np.r_[True, cid[order][1:] != cid[order][:-1]]]
            rest = np.setdiff1d(np.arange(len(p)), first)
            keep = np.concatenate([first[np.argsort(s[first], kind="stable")], rest[np.argsort(s[rest], kind="stable")]])
            keep = keep[: self.max_points]
            p, s = p[keep], s[keep]
        self.pools[submap_id] = (p, s)
        return len(p)

    def pop(self, submap_id: int) -> tuple[np.ndarray, np.ndarray] | None:
        return self.pools.pop(submap_id, None)
