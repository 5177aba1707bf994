"""Colour maps of the viewer: per-submap colours, height colouring, depth/sigma images. numpy + OpenCV only."""

from __future__ import annotations

import cv2
import numpy as np

GOLDEN = 0.618033988749895


def submap_color(submap_id: int) -> np.ndarray:
    """A saturated RGB colour (uint8, (3,)) per submap id; neighbouring ids get distant hues."""
    hue = (int(submap_id) * GOLDEN) % 1.0
    hsv = np.array([[[hue * 180.0, 200.0, 235.0]]], np.float32)
    return cv2.cvtColor(hsv.astype(np.uint8), cv2.COLOR_HSV2RGB)[0, 0]


def colormap(values: np.ndarray, lo: float, hi: float, cmap: int = cv2.COLORMAP_TURBO,
             invalid: tuple[int, int, int] = (0, 0, 0)) -> np.ndarray:
    """RGB uint8 of ``values`` (any shape) mapped linearly from [lo, hi] through an OpenCV colour map;
    non-finite values get ``invalid``. Output shape: values.shape + (3,)."""
    v = np.asarray(values, np.float64)
    if hi <= lo:
        raise ValueError(f"colour map range must have hi > lo, got [{lo}, {hi}]")
    finite = np.isfinite(v)
    idx = np.clip((np.where(finite, v, lo) - lo) / (hi - lo), 0.0, 1.0)
    idx = np.round(idx * 255.0).astype(np.uint8).reshape(-1, 1)
    bgr = cv2.applyColorMap(idx, cmap).reshape(v.shape + (3,))
    rgb = bgr[..., ::-1].copy()
    rgb[~finite] = invalid
    return rgb


def height_colors(z: np.ndarray, z_range: tuple[float, float]) -> np.ndarray:
    """Per-vertex RGB (N,3) uint8 from heights z (N,) in W [m]."""
    return colormap(z, z_range[0], z_range[1])


def depth_image(depth: np.ndarray, depth_range: tuple[float, float]) -> np.ndarray:
    """Colour-mapped depth (H,W,3) uint8: near is the warm (red) end of turbo, far the blue end; NaN black."""
    return colormap(-np.asarray(depth, np.float64), -depth_range[1], -depth_range[0])


def sigma_image(sigma: np.ndarray, sigma_range: tuple[float, float]) -> np.ndarray:
    """Colour-mapped depth sigma (H,W,3) uint8 (low = dark, high = bright); NaN black."""
    return colormap(sigma, sigma_range[0], sigma_range[1], cv2.COLORMAP_INFERNO)


def gray_to_rgb(image: np.ndarray) -> np.ndarray:
    """(H,W) uint8 grayscale to (H,W,3); colour images pass through."""
    im = np.asarray(image)
    if im.ndim == 2:
        return np.repeat(im[..., None], 3, axis=2)
    if im.ndim == 3 and im.shape[2] == 3:
        return im
    raise ValueError(f"expected a (H,W) or (H,W,3) image, got shape {im.shape}")
