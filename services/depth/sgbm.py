"""Classical baseline: OpenCV semi-global matching on a rectified pair, with heuristic depth sigma.

The heuristic models are supereight2's: 'quadratic' (a constant disparity sigma sigma_u propagated by
eq. 11, sigma_d = sigma_u d^2 / (f b)) and 'linear' (sigma_d = k d). This is the paper's "heuristic sigma"
row and the depth service's fallback when no network weights exist.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from services.depth.uncertainty import disparity_to_depth, heuristic_sigma


@dataclass(frozen=True)
class SgbmParams:
    num_disparities: int = 96  # [px], multiple of 16
    block_size: int = 5  # [px], odd
    uniqueness_ratio: int = 10  # [%]
    speckle_window: int = 100  # [px]
    speckle_range: int = 2  # [px]
    disp12_max_diff: int = 1  # [px]


def sgbm_disparity(left: np.ndarray, right: np.ndarray, params: SgbmParams = SgbmParams()) -> np.ndarray:
    """Rectified uint8 grey images (H,W) -> disparity [px] float32 (H,W), NaN where SGBM found none."""
    if left.shape != right.shape or left.ndim != 2:
        raise ValueError(f"need two grey images of the same size, got {left.shape} and {right.shape}")
    b = params.block_size
    matcher = cv2.StereoSGBM_create(
        minDisparity=0, numDisparities=params.num_disparities, blockSize=b, P1=8 * b * b, P2=32 * b * b,
        disp12MaxDiff=params.disp12_max_diff, uniquenessRatio=params.uniqueness_ratio,
        speckleWindowSize=params.speckle_window, speckleRange=params.speckle_range, mode=cv2.STEREO_SGBM_MODE_SGBM)
    disp = matcher.compute(np.ascontiguousarray(left, np.uint8), np.ascontiguousarray(right, np.uint8))
    disp = disp.astype(np.float32) / 16.0  # fixed point with 4 fractional bits
    disp[disp <= 0] = np.nan
    return disp


def fill_background(disp: np.ndarray) -> np.ndarray:
    """Holes (NaN) take the smaller of the nearest valid disparities to their left and right on the same row (the
    background side of an occlusion); rows without any valid pixel take the image's median (0 if none)."""
    d = np.asarray(disp, np.float32)
    valid = np.isfinite(d)
    h, w = d.shape
    cols = np.arange(w)[None, :].repeat(h, 0)
    rows = np.arange(h)[:, None]
    left_idx = np.maximum.accumulate(np.where(valid, cols, -1), axis=1)
    right_idx = np.flip(np.minimum.accumulate(np.flip(np.where(valid, cols, w), 1), axis=1), 1)
    from_left = np.where(left_idx >= 0, d[rows, np.clip(left_idx, 0, w - 1)], np.inf)
    from_right = np.where(right_idx < w, d[rows, np.clip(right_idx, 0, w - 1)], np.inf)
    fill = np.minimum(from_left, from_right)
    default = float(np.nanmedian(d)) if valid.any() else 0.0
    return np.where(valid, d, np.where(np.isfinite(fill), fill, default)).astype(np.float32)


def sgbm_depth(left: np.ndarray, right: np.ndarray, f_px: float, baseline_m: float, sigma_model: str = "quadratic",
               sigma_coeff: float = 1.0, params: SgbmParams = SgbmParams()) -> tuple[np.ndarray, np.ndarray]:
    """Depth [m] and heuristic sigma [m]. ``sigma_coeff``: the disparity sigma [px] for 'quadratic',
    the relative depth sigma k [-] for 'linear'."""
    disp = sgbm_disparity(left, right, params)
    depth, _ = disparity_to_depth(disp, np.zeros_like(disp), f_px, baseline_m)
    return depth, stereo_heuristic_sigma(depth, f_px, baseline_m, sigma_model, sigma_coeff)


def stereo_heuristic_sigma(depth: np.ndarray, f_px: float, baseline_m: float, sigma_model: str = "quadratic",
                           sigma_coeff: float = 1.0) -> np.ndarray:
    """Heuristic sigma [m] (H,W) float32 of a stereo depth map [m], NaN where the depth is: 'quadratic' with a
    disparity sigma of ``sigma_coeff`` px (sigma_d = d^2 sigma_u / (f b)), 'linear' sigma_d = ``sigma_coeff`` d."""
    if sigma_model == "quadratic":
        sigma = heuristic_sigma(depth, "quadratic", sigma_coeff / (f_px * baseline_m))
    else:
        sigma = heuristic_sigma(depth, sigma_model, sigma_coeff)
    return np.where(np.isfinite(depth), sigma, np.nan).astype(np.float32)
