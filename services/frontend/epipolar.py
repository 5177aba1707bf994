"""Two-view geometry of a calibrated rig: cross-camera epipolar distances, ray triangulation, RANSAC."""

from __future__ import annotations

import cv2
import numpy as np

from shared.camera import CameraCalib, CameraModel
from shared.geometry import inv_T, skew


def overlapping_pairs(calibs: list[CameraCalib], min_cos: float) -> list[tuple[int, int]]:
    """Ordered pairs (i, j), i != j, whose optical axes make an angle with cosine above ``min_cos``."""
    z = [np.asarray(c.T_SC)[:3, 2] for c in calibs]
    return [(i, j) for i in range(len(calibs)) for j in range(len(calibs))
            if i != j and float(z[i] @ z[j]) > min_cos]


def essential(T_CjCi: np.ndarray) -> np.ndarray:
    """E with x_j^T E x_i = 0 for normalised homogeneous coordinates of one point in cameras i and j."""
    return skew(T_CjCi[:3, 3]) @ T_CjCi[:3, :3]


def epipolar_distance(E_ji: np.ndarray, x_i: np.ndarray, x_j: np.ndarray) -> np.ndarray:
    """Distance (normalised units) of x_j (N,2) to the epipolar line of x_i (N,2) in camera j."""
    hi = np.c_[x_i, np.ones(len(x_i))]
    hj = np.c_[x_j, np.ones(len(x_j))]
    lines = hi @ E_ji.T
    return np.abs(np.sum(lines * hj, axis=1)) / np.maximum(np.linalg.norm(lines[:, :2], axis=1), 1e-12)


def ray_depths(T_CiCj: np.ndarray, x_i: np.ndarray, x_j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depths (z) of the closest points of the rays of x_i (in Ci) and x_j (in Cj): a_i d_i ~ t + a_j R d_j."""
    d_i = np.c_[x_i, np.ones(len(x_i))]
    d_j = np.c_[x_j, np.ones(len(x_j))] @ T_CiCj[:3, :3].T
    t = T_CiCj[:3, 3]
    a11 = np.sum(d_i * d_i, 1)
    a12 = -np.sum(d_i * d_j, 1)
    a22 = np.sum(d_j * d_j, 1)
    b1 = d_i @ t
    b2 = -(d_j @ t)
    det = a11 * a22 - a12 * a12
    with np.errstate(divide="ignore", invalid="ignore"):
        zi = (a22 * b1 - a12 * b2) / det
        zj = (a11 * b2 - a12 * b1) / det
    zi = np.where(np.abs(det) > 1e-12, zi, np.inf)
    zj = np.where(np.abs(det) > 1e-12, zj, np.inf)
    return zi, zj


def cross_camera_check(cam_i: CameraCalib, cam_j: CameraCalib, uv_i: np.ndarray, uv_j: np.ndarray,
                       max_px: float, min_depth_m: float) -> np.ndarray:
    """Mask of matches consistent with the extrinsics: epipolar distance below ``max_px`` (in camera j's
    pixels) and the triangulated point in front of both cameras, farther than ``min_depth_m``."""
    if len(uv_i) == 0:
        return np.zeros(0, bool)
    T_CjCi = inv_T(cam_j.T_SC) @ cam_i.T_SC
    x_i = cam_i.camera.unproject(uv_i)[:, :2]
    x_j = cam_j.camera.unproject(uv_j)[:, :2]
    d = epipolar_distance(essential(T_CjCi), x_i, x_j) * cam_j.camera.fx
    zi, zj = ray_depths(inv_T(T_CjCi), x_i, x_j)
    return (d <= max_px) & (zi > min_depth_m) & (zj > min_depth_m)


def ransac_inliers(camera: CameraModel, uv0: np.ndarray, uv1: np.ndarray, threshold_px: float,
                   confidence: float) -> np.ndarray:
    """Inlier mask of a fundamental-matrix RANSAC on undistorted pixels (all True with fewer than 8 matches)."""
    n = len(uv0)
    if n < 8:
        return np.ones(n, bool)
    p0 = camera.undistort_points(uv0).astype(np.float32)
    p1 = camera.undistort_points(uv1).astype(np.float32)
    _, mask = cv2.findFundamentalMat(p0, p1, cv2.FM_RANSAC, threshold_px, confidence)
    if mask is None:
        return np.ones(n, bool)
    return mask.ravel().astype(bool)
