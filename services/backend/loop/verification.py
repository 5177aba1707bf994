"""Geometric verification of a loop candidate: 3D-2D RANSAC of the current keyframe against the landmarks
the old keyframe observed.

Descriptors of the current keyframe are matched to the old keyframe's descriptors whose landmark has a 3D
position (mutual nearest neighbours under the Hamming distance, with a distance bound). The body pose
``T_WS`` of the current keyframe in the old keyframe's world frame comes from ``cv2.solvePnPRansac`` on the
camera with most matches (normalised coordinates, so any distortion model works), refined over the inliers
of all cameras by Gauss-Newton; the loop is accepted only with enough inliers and inlier share. The pose's
covariance is the inverse of the reprojection information of the inliers (sigma_px), inflated by
``cov_inflation`` to account for the landmarks' own uncertainty.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from shared.geometry import inv_T, skew, so3_exp
from services.backend.loop.vocabulary import hamming


@dataclass(frozen=True)
class FeatureSet:
    """Features of one keyframe: distorted pixels per camera and their ORB descriptors."""

    landmark_ids: np.ndarray  # (K,) int64
    camera_index: np.ndarray  # (K,) int
    uv: np.ndarray  # (K,2) distorted pixels
    descriptors: np.ndarray  # (K,32) uint8


@dataclass(frozen=True)
class PnpResult:
    accepted: bool
    reason: str
    matches: int
    inliers: int
    T_WS: np.ndarray | None = None  # current body pose in the old keyframe's world frame
    covariance: np.ndarray | None = None  # (6,6) of T_WS, gtsam Pose3 tangent order [rot_S, t_S]
    query_index: np.ndarray | None = None  # (I,) inlier features of the query ...
    old_index: np.ndarray | None = None  # (I,) ... and the old keyframe's features they match


def mutual_matches(a: np.ndarray, b: np.ndarray, max_distance: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices (ia, ib) of mutual nearest neighbours between descriptor sets a and b within max_distance bits."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    d = hamming(a, b)
    ab, ba = np.argmin(d, axis=1), np.argmin(d, axis=0)
    ia = np.flatnonzero((ba[ab] == np.arange(len(a))) & (d[np.arange(len(a)), ab] <= max_distance))
    return ia, ab[ia]


def _residuals_jacobian(T_WS, p_W, xy, T_SC_per_obs):
    """Normalised reprojection residuals (M,2) and their Jacobian (M,2,6) w.r.t. a right perturbation
    [omega, v] of T_WS (gtsam Pose3 convention)."""
    T_SW = inv_T(T_WS)
    p_S = p_W @ T_SW[:3, :3].T + T_SW[:3, 3]
    T_CS = np.array([inv_T(T) for T in T_SC_per_obs])
    p_C = np.einsum("mij,mj->mi", T_CS[:, :3, :3], p_S) + T_CS[:, :3, 3]
    z = p_C[:, 2]
    r = p_C[:, :2] / z[:, None] - xy
    dproj = np.zeros((len(z), 2, 3))
    dproj[:, 0, 0] = dproj[:, 1, 1] = 1 / z
    dproj[:, :, 2] = -p_C[:, :2] / z[:, None] ** 2
    dpS = np.concatenate([np.array([skew(p) for p in p_S]), -np.broadcast_to(np.eye(3), (len(z), 3, 3))], axis=2)
    J = np.einsum("mij,mjk,mkl->mil", dproj, T_CS[:, :3, :3], dpS)
    return r, J, z


def verify_pnp(query: FeatureSet, old: FeatureSet, old_p_W: np.ndarray, undistort, T_SC: np.ndarray,
               focal_px: np.ndarray, sigma_px: float = 1.0, max_hamming: int = 50, ransac_px: float = 3.0,
               min_inliers: int = 20, min_inlier_ratio: float = 0.3, cov_inflation: float = 4.0) -> PnpResult:
    """Verify that ``query`` sees the landmarks of ``old`` (positions ``old_p_W`` (K,3), NaN where unknown).

    ``undistort[c]`` maps distorted pixels (M,2) of camera c to normalised coordinates; ``T_SC`` (C,4,4);
    ``focal_px`` (C,) converts pixel thresholds to normalised units."""
    known = np.flatnonzero(np.all(np.isfinite(old_p_W), axis=1))
    iq, io = mutual_matches(query.descriptors, old.descriptors[known], max_hamming)
    io = known[io]
    m = len(iq)
    if m < min_inliers:
        return PnpResult(False, "too few descriptor matches", m, 0)
    cams = np.asarray(query.camera_index, np.int64)[iq]
    xy = np.zeros((m, 2))
    for c in np.unique(cams):
        sel = cams == c
        xy[sel] = undistort[c](np.asarray(query.uv, float)[iq][sel])
    p_W = np.asarray(old_p_W, float)[io]
    best_c = int(np.bincount(cams).argmax())
    sel = np.flatnonzero(cams == best_c)
    if len(sel) < 6:
        return PnpResult(False, "too few matches in one camera", m, 0)
    thr = ransac_px / float(focal_px[best_c])
    ok, rvec, tvec, inl = cv2.solvePnPRansac(p_W[sel], xy[sel], np.eye(3), None, reprojectionError=thr,
                                             iterationsCount=200, confidence=0.999, flags=cv2.SOLVEPNP_EPNP)
    if not ok or inl is None or len(inl) < 6:
        return PnpResult(False, "RANSAC found no pose", m, 0 if inl is None else len(inl))
    T_CW = np.eye(4)
    T_CW[:3, :3], T_CW[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
    T_WS = inv_T(T_CW) @ inv_T(T_SC[best_c])
    T_SC_obs = np.asarray(T_SC)[cams]
    f_obs = np.asarray(focal_px, float)[cams]
    inliers = np.zeros(m, bool)
    for _ in range(5):  # Gauss-Newton over the inliers of all cameras
        r, J, z = _residuals_jacobian(T_WS, p_W, xy, T_SC_obs)
        err_px = np.linalg.norm(r, axis=1) * f_obs
        inliers = (z > 0) & (err_px < ransac_px)
        if inliers.sum() < 6:
            break
        w = (f_obs[inliers] / sigma_px)[:, None, None]
        Jw, rw = (J[inliers] * w).reshape(-1, 6), (r[inliers] * w[:, :, 0]).reshape(-1)
        dx = np.linalg.lstsq(Jw, -rw, rcond=None)[0]
        T_WS = T_WS.copy()
        dT = np.eye(4)
        dT[:3, :3], dT[:3, 3] = so3_exp(dx[:3]), dx[3:]
        T_WS = T_WS @ dT
    n_in = int(inliers.sum())
    if n_in < min_inliers or n_in < min_inlier_ratio * m:
        return PnpResult(False, f"{n_in} inliers of {m} matches", m, n_in, T_WS)
    r, J, _ = _residuals_jacobian(T_WS, p_W[inliers], xy[inliers], T_SC_obs[inliers])
    w = (f_obs[inliers] / sigma_px)[:, None, None]
    Jw = (J * w).reshape(-1, 6)
    info = Jw.T @ Jw
    try:
        cov = np.linalg.inv(info) * cov_inflation
    except np.linalg.LinAlgError:
        return PnpResult(False, "degenerate inlier geometry", m, n_in, T_WS)
    return PnpResult(True, "accepted", m, n_in, T_WS, 0.5 * (cov + cov.T), iq[inliers], io[inliers])
