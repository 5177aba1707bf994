"""Sparse depth prior of the MVS network from the estimator's landmarks (paper sec. IV-D, V-A): landmarks
projected into the reference camera, one depth per pixel (the nearest landmark wins), 0 elsewhere, as
``MVSNet`` expects (it was trained with 20-300 such pixels, ``tools/depth/train.py``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shared.geometry import inv_T, transform_points


@dataclass(frozen=True)
class LandmarkPrior:
    depth: np.ndarray  # (H,W) float32 [m], 0 where no landmark
    used: int  # pixels holding a landmark depth
    rejected: int  # landmarks outside the image or the depth range, sharing a pixel, or over max_points


def landmark_prior(p_W: np.ndarray, T_WC: np.ndarray, K: np.ndarray, shape_hw: tuple[int, int],
                   min_depth_m: float, max_depth_m: float, max_points: int,
                   priority: np.ndarray | None = None) -> LandmarkPrior:
    """Project landmarks ``p_W`` (N,3) [m] into the pinhole camera ``K`` at pose ``T_WC``.

    A landmark is kept when its depth z is within [min_depth_m, max_depth_m] and its pixel (the nearest pixel
    centre, centres at integer coordinates) lies inside the image. Of several landmarks in one pixel the
    nearest is kept. Beyond ``max_points`` kept pixels those with the highest ``priority`` (e.g. observation
    count; ties and no priority: input order) stay."""
    h, w = shape_hw
    p_W = np.asarray(p_W, np.float64).reshape(-1, 3)
    prior = np.zeros((h, w), np.float32)
    if len(p_W) == 0 or max_points <= 0:
        return LandmarkPrior(prior, 0, len(p_W))
    p_C = transform_points(inv_T(np.asarray(T_WC, np.float64)), p_W)
    z = p_C[:, 2]
    ok = np.isfinite(p_C).all(axis=1) & (z >= min_depth_m) & (z <= max_depth_m)
    zs = np.where(ok, z, 1.0)
    u = np.floor(K[0, 0] * p_C[:, 0] / zs + K[0, 2] + 0.5)
    v = np.floor(K[1, 1] * p_C[:, 1] / zs + K[1, 2] + 0.5)
    ok &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
    idx = np.flatnonzero(ok)
    pri = np.zeros(len(p_W)) if priority is None else np.asarray(priority, np.float64).reshape(-1)
    if len(pri) != len(p_W):
        raise ValueError(f"priority of length {len(pri)} for {len(p_W)} landmarks")
    # order: highest priority first, then nearest; the first landmark per pixel wins
    idx = idx[np.lexsort((z[idx], -pri[idx]))]
    pix = v[idx].astype(np.int64) * w + u[idx].astype(np.int64)
    _, first = np.unique(pix, return_index=True)
    # the nearest landmark of a pixel is kept even when a farther one has a higher priority
    nearest = np.full(h * w, np.inf)
    np.minimum.at(nearest, pix, z[idx])
    keep = idx[np.sort(first)][:max_points]
    pix_keep = v[keep].astype(np.int64) * w + u[keep].astype(np.int64)
    prior.ravel()[pix_keep] = nearest[pix_keep]
    return LandmarkPrior(prior, len(keep), len(p_W) - len(keep))
