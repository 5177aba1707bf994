"""Depth pixels too uncertain to place a surface, which still say that the space well in front of them is free.

A learned sigma that exceeds a fraction k of its depth (depth.max_relative_sigma, stamped on every DepthFrame as
``surface_max_relative_sigma``) marks a pixel whose depth the map should not draw as a surface: at the stereo
network's far range such pixels are where the phantom surfaces in front of and behind the true ones come from
(docs/mapping.md). Dropping them also dropped what they still know: the ray up to ``depth - 3 sigma`` is free. The
mapper integrates them as free space only (services/mapping/integrate.py)."""

from __future__ import annotations

import numpy as np


def carve_only_pixels(depth: np.ndarray, sigma: np.ndarray, max_relative_sigma: float) -> np.ndarray | None:
    """Pixels (H, W) bool whose sigma exceeds ``max_relative_sigma`` x depth (NaN pixels: False); None when the rule
    is off (<= 0)."""
    if not max_relative_sigma > 0:
        return None
    with np.errstate(invalid="ignore"):
        return np.asarray(sigma) > max_relative_sigma * np.asarray(depth)


def surface_depth(depth: np.ndarray, sigma: np.ndarray, max_relative_sigma: float) -> np.ndarray:
    """The depth with NaN where it places no surface (:func:`carve_only_pixels`): what users of depth points want."""
    carve = carve_only_pixels(depth, sigma, max_relative_sigma)
    return depth if carve is None else np.where(carve, np.float32(np.nan), depth).astype(np.float32)
