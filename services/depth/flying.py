"""Flying pixels: depth between the near and the far side of a depth edge.

A stereo or MVS network predicts depth at a fraction of the image's resolution and upsamples it, so across the
silhouette of an object its depth runs from the object to the background over a few pixels. Those pixels lie on
neither surface: integrated, they draw a curtain from the object's edge to the wall behind it. At ground-truth poses
on the V1_02 replica they are a few per cent of the stereo network's pixels and a quarter of its summed depth error
(``python -m tools.map_error``, docs/depth.md).

A depth edge is where, within ``radius_px`` of a pixel, the depth spans more than ``rel_jump`` of the pixel's
depth. A surface seen at a grazing angle far away spans that much too (a floor 5 m away, seen from 1.5 m up, drops
about 5 cm per pixel row), but its disparity (``f b / depth``) changes slowly: the edge must also change the
disparity by more than ``min_gradient`` pixels per pixel (that floor: about 0.07 with the EuRoC rig at 512 px; the
replica's object silhouettes: 0.25 at the median). A pixel at such an edge is flying when its disparity lies more than
``margin`` of the window's span away from both ends: the object's own pixels and the background's stay.
"""

from __future__ import annotations

import cv2
import numpy as np

_BIG = np.float32(1e6)


def flying_pixels(depth: np.ndarray, f_b: float, radius_px: int, rel_jump: float, min_gradient: float,
                  margin: float) -> np.ndarray:
    """Mask (H, W) of the flying pixels of ``depth`` (H, W [m]; NaN = none, never flying). ``f_b``: focal length
    [px] times baseline [m], which turns inverse depth into disparity [px]. All False for radius 0."""
    d = np.asarray(depth, np.float32)
    if radius_px <= 0:
        return np.zeros(d.shape, bool)
    valid = np.isfinite(d) & (d > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        disp = np.where(valid, np.float32(f_b) / d, np.float32(np.nan))
    window = np.ones((2 * radius_px + 1,) * 2, np.uint8)
    lo = cv2.erode(np.where(valid, disp, _BIG), window)  # the farthest surface around each pixel (NaN ignored)
    hi = cv2.dilate(np.where(valid, disp, -_BIG), window)  # the nearest
    span = hi - lo
    with np.errstate(invalid="ignore", divide="ignore"):
        depth_span = f_b / lo - f_b / hi
        edge = (depth_span > rel_jump * d) & (span > min_gradient * 2 * radius_px)
        return valid & edge & (disp - lo > margin * span) & (hi - disp > margin * span)
