"""Pyramidal Lucas-Kanade tracking with an initial guess and a forward-backward check."""

from __future__ import annotations

import cv2
import numpy as np

from shared.camera import CameraModel


def track(img0: np.ndarray, img1: np.ndarray, uv0: np.ndarray, guess: np.ndarray | None,
          window_px: int, levels: int, iterations: int, fb_max_px: float, size: tuple[int, int],
          fb_levels: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Track ``uv0`` (N,2) from image 0 into image 1 starting at ``guess``; returns uv1 (N,2) and a mask
    of tracks that converged both ways, came back within ``fb_max_px`` and stay inside the image (w, h).

    The return track starts at ``uv0`` and runs on ``fb_levels`` pyramid levels (None: ``levels``). A track can
    only pass when it comes back within ``fb_max_px`` of where it started, well inside the basin of the full image
    alone, so 0 levels decide the check as the whole pyramid does at a third of the cost (no pyramids to build)."""
    n = len(uv0)
    if n == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    p0 = np.ascontiguousarray(uv0, np.float32).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, iterations, 0.01)
    win = (window_px, window_px)
    flags = 0
    p1 = None
    if guess is not None:
        p1 = np.ascontiguousarray(guess, np.float32).reshape(-1, 1, 2).copy()
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(img0, img1, p0, p1, winSize=win, maxLevel=levels, criteria=crit, flags=flags)
    p0b, st0, _ = cv2.calcOpticalFlowPyrLK(img1, img0, p1, p0.copy(), winSize=win,
                                           maxLevel=levels if fb_levels is None else fb_levels, criteria=crit,
                                           flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    uv1 = p1.reshape(-1, 2)
    w, h = size
    fb = np.linalg.norm(p0b.reshape(-1, 2) - p0.reshape(-1, 2), axis=1)
    ok = ((st1.ravel() == 1) & (st0.ravel() == 1) & (fb <= fb_max_px) & np.all(np.isfinite(uv1), axis=1)
          & (uv1[:, 0] >= 0) & (uv1[:, 0] <= w - 1) & (uv1[:, 1] >= 0) & (uv1[:, 1] <= h - 1))
    return uv1, ok


def predict_rotated(camera: CameraModel, uv: np.ndarray, R_C1C0: np.ndarray) -> np.ndarray:
    """Where pixels of camera 0 appear in camera 1 when the two differ by the rotation R_C1C0 only (points at
    infinity); pixels whose prediction leaves the image keep their position."""
    if len(uv) == 0:
        return np.zeros((0, 2), np.float32)
    rays = camera.unproject(uv) @ np.asarray(R_C1C0, float).T
    pred, valid = camera.project(rays)
    return np.where(valid[:, None], pred, uv).astype(np.float32)


def normalised_gain(image: np.ndarray, mean_dn: float) -> np.ndarray:
    """``image`` (uint8) scaled so that its mean grey level is ``mean_dn`` (a global gain; saturates at 255)."""
    m = float(image.mean())
    if m <= 1.0:
        return image
    return cv2.convertScaleAbs(image, alpha=mean_dn / m)


def gain_matched(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pair (a, b) of uint8 images with the brighter one scaled to the darker one's mean grey level (a global
    gain, scaled down so nothing saturates): KLT between them then sees one brightness."""
    ma, mb = float(a.mean()), float(b.mean())
    if ma <= 1.0 or mb <= 1.0 or ma == mb:
        return a, b
    if ma > mb:
        return cv2.convertScaleAbs(a, alpha=mb / ma), b
    return a, cv2.convertScaleAbs(b, alpha=ma / mb)
