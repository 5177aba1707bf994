"""Which pixels of a rectified (or undistorted) image carry image content.

Rectification maps pixels of the new pinhole image back into the raw camera; near the corners and the top and
bottom edges many of them land outside the raw image and are filled with black. The depth networks were
trained on fully covered images and make up a depth for those pixels (the MVS network mostly far beyond the
true surface, with a moderate sigma), and their receptive field carries the error a few pixels into the
covered area. Depth is therefore only kept on covered pixels at least ``margin_px`` from an uncovered one.
"""
from __future__ import annotations

import cv2
import numpy as np


def covered(maps: tuple[np.ndarray, np.ndarray], raw_hw: tuple[int, int]) -> np.ndarray:
    """(H,W) bool of the remapped image: True where ``cv2.remap`` with ``maps`` (the (map_x, map_y) pair
    of shared.camera, float32 [px]) samples inside a raw image of ``raw_hw`` = (h, w) (bilinear: the whole
    2x2 neighbourhood inside)."""
    mx, my = (np.asarray(m, np.float64) for m in maps)
    h, w = raw_hw
    with np.errstate(invalid="ignore"):
        return np.isfinite(mx) & np.isfinite(my) & (mx >= 0) & (mx <= w - 1) & (my >= 0) & (my <= h - 1)


def valid_region(masks: list[np.ndarray], margin_px: int) -> np.ndarray:
    """Pixels covered in every mask and at least ``margin_px`` [px] (chessboard distance) from any pixel that
    is not; the image edge itself counts as covered (only uncovered pixels push the border in)."""
    if margin_px < 0:
        raise ValueError(f"margin_px must be >= 0, got {margin_px}")
    m = np.logical_and.reduce([np.asarray(x, bool) for x in masks])
    if margin_px == 0 or m.all():
        return m
    k = np.ones((2 * margin_px + 1, 2 * margin_px + 1), np.uint8)
    return cv2.erode(m.astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=1) > 0


def stereo_valid(rect, raw_hw: tuple[tuple[int, int], tuple[int, int]], margin_px: int) -> np.ndarray:
    """:func:`valid_region` of a rectified pair (``rect`` from shared.camera.stereo_rectification): pixels covered
    by both raw images of ``raw_hw`` = ((h0, w0), (h1, w1)), ``margin_px`` [px] away from uncovered ones."""
    return valid_region([covered(rect.maps0, raw_hw[0]), covered(rect.maps1, raw_hw[1])], margin_px)
