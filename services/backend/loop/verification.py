"""Geometric verification of a loop candidate: 3D-2D RANSAC of the current keyframe against the landmarks
the old keyframe observed.

Descriptors of the current keyframe are matched to the old keyframe's descriptors whose landmark has a 3D
position (mutual nearest neighbours under the Hamming distance, with a distance bound). The body pose
``T_WS`` of the current keyframe in the old keyframe's world frame comes from ``cv2.solvePnPRansac`` on the
camera with most matches (normalised coordinates, so any distortion model works), refined over the inliers
of all cameras by Gauss-Newton; the loop is accepted only with enough inliers and inlier share. The pose's
covariance is the inverse of the reprojection information of the inliers (sigma_px), inflated by
``cov_inflation`` to account for the landmarks' own uncertainty.

Guided matching (``guide``): a pose with at least ``guide.seed_inliers`` inliers, too few to accept, is a seed.
The landmarks of a wider set (the candidate and more of its neighbours) are projected into the query's cameras at
the seed pose, each query feature is matched to the landmark of smallest Hamming distance that falls within
``guide.radius_px`` of it (mutually), and the pose is refined again over these matches. A true revisit seen from
a few metres or degrees away shares few *mutual nearest neighbours* with the old keyframe, but many of its
features lie where the old landmarks project; a wrong seed finds few matches where it projects them.
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
    old_index: np.ndarray | None = None  # (I,) ... and the old keyframe's features they match (the guide's: expanded)
    expanded: bool = False  # the pose was expanded by guided matching


class Guide:
    """Guided matching of :func:`verify_pnp`: the wider set whose landmarks are projected at a seed pose.

    ``features`` and ``p_W`` ((K,3) positions of the set's landmarks, NaN where unknown) are given, or ``load()``
    returns them the first time they are needed: most candidates never give a seed. A RANSAC pose with at least
    ``seed_inliers`` inliers is expanded; a query feature matches landmarks projecting within ``radius_px``."""

    def __init__(self, features: FeatureSet | None = None, p_W: np.ndarray | None = None, seed_inliers: int = 12,
                 radius_px: float = 12.0, load=None) -> None:
        self._set = None if features is None else (features, p_W)
        self._load = load
        self.seed_inliers, self.radius_px = int(seed_inliers), float(radius_px)

    def wide_set(self) -> tuple[FeatureSet, np.ndarray]:
        if self._set is None:
            self._set = self._load()
        return self._set

    @property
    def features(self) -> FeatureSet:
        return self.wide_set()[0]

    @property
    def p_W(self) -> np.ndarray:
        return self.wide_set()[1]


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


def match_by_projection(T_WS: np.ndarray, cams: np.ndarray, xy: np.ndarray, desc: np.ndarray, p_W: np.ndarray,
                        p_desc: np.ndarray, T_SC: np.ndarray, focal_px: np.ndarray, radius_px: float,
                        max_hamming: int) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (iq, il) of query features (camera ``cams``, normalised ``xy``, descriptors ``desc``) and landmarks
    (``p_W`` (L,3), descriptors ``p_desc``) seen by body pose ``T_WS``: each query feature with the landmark of
    smallest Hamming distance (at most ``max_hamming``) among those projecting in front of its camera within
    ``radius_px`` of it, kept when that feature is also the landmark's best."""
    nq, nl = len(cams), len(p_W)
    if nq == 0 or nl == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    T_SW = inv_T(T_WS)
    p_S = p_W @ T_SW[:3, :3].T + T_SW[:3, 3]
    far = np.iinfo(np.int32).max
    cost = np.full((nq, nl), far, np.int32)
    h = hamming(desc, p_desc)
    for c in np.unique(cams):
        T_CS = inv_T(T_SC[c])
        p_C = p_S @ T_CS[:3, :3].T + T_CS[:3, 3]
        front = p_C[:, 2] > 1e-3
        proj = p_C[:, :2] / np.where(front, p_C[:, 2], 1.0)[:, None]
        qi = np.flatnonzero(cams == c)
        d2 = ((xy[qi, None, :] - proj[None, :, :]) ** 2).sum(axis=2) * float(focal_px[c]) ** 2
        near = (d2 <= radius_px ** 2) & front[None, :]
        cost[qi] = np.where(near, h[qi], far)
    best_l = np.argmin(cost, axis=1)
    best_q = np.argmin(cost, axis=0)
    ok = (cost[np.arange(nq), best_l] <= max_hamming) & (best_q[best_l] == np.arange(nq))
    iq = np.flatnonzero(ok)
    return iq, best_l[iq]


def _refine(T_WS, p_W, xy, T_SC_obs, f_obs, ransac_px, sigma_px, iterations=5):
    """Gauss-Newton of body pose ``T_WS`` over the matches within ``ransac_px`` (re-selected each step). Returns
    (T_WS, inlier mask)."""
    inliers = np.zeros(len(p_W), bool)
    for _ in range(iterations):
        r, J, z = _residuals_jacobian(T_WS, p_W, xy, T_SC_obs)
        err_px = np.linalg.norm(r, axis=1) * f_obs
        inliers = (z > 0) & (err_px < ransac_px)
        if inliers.sum() < 6:
            break
        w = (f_obs[inliers] / sigma_px)[:, None, None]
        Jw, rw = (J[inliers] * w).reshape(-1, 6), (r[inliers] * w[:, :, 0]).reshape(-1)
        dx = np.linalg.lstsq(Jw, -rw, rcond=None)[0]
        dT = np.eye(4)
        dT[:3, :3], dT[:3, 3] = so3_exp(dx[:3]), dx[3:]
        T_WS = T_WS @ dT
    return T_WS, inliers


def normalised_xy(fs: FeatureSet, undistort, index: np.ndarray | None = None) -> np.ndarray:
    """Normalised coordinates (M,2) of the features ``index`` (all: None) of ``fs``."""
    index = np.arange(len(fs.camera_index)) if index is None else index
    cams, uv = np.asarray(fs.camera_index, np.int64)[index], np.asarray(fs.uv, float)[index]
    xy = np.zeros((len(index), 2))
    for c in np.unique(cams):
        xy[cams == c] = undistort[c](uv[cams == c])
    return xy


def verify_pnp(query: FeatureSet, old: FeatureSet, old_p_W: np.ndarray, undistort, T_SC: np.ndarray,
               focal_px: np.ndarray, sigma_px: float = 1.0, max_hamming: int = 50, ransac_px: float = 3.0,
               min_inliers: int = 20, min_inlier_ratio: float = 0.3, cov_inflation: float = 4.0,
               guide: Guide | None = None) -> PnpResult:
    """Verify that ``query`` sees the landmarks of ``old`` (positions ``old_p_W`` (K,3), NaN where unknown).

    ``undistort[c]`` maps distorted pixels (M,2) of camera c to normalised coordinates; ``T_SC`` (C,4,4);
    ``focal_px`` (C,) converts pixel thresholds to normalised units. With ``guide``, a seed pose is expanded by
    guided matching (module doc); the result's ``old_index`` then indexes ``guide.features``."""
    seed = min_inliers if guide is None else min(min_inliers, guide.seed_inliers)
    known = np.flatnonzero(np.all(np.isfinite(old_p_W), axis=1))
    iq, io = mutual_matches(query.descriptors, old.descriptors[known], max_hamming)
    io = known[io]
    m = len(iq)
    if m < seed:
        return PnpResult(False, "too few descriptor matches", m, 0)
    cams = np.asarray(query.camera_index, np.int64)[iq]
    xy = normalised_xy(query, undistort, iq)
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
    T_SC = np.asarray(T_SC)
    focal_px = np.asarray(focal_px, float)
    T_WS, inliers = _refine(T_WS, p_W, xy, T_SC[cams], focal_px[cams], ransac_px, sigma_px)
    n_in = int(inliers.sum())
    expanded = guide is not None and guide.seed_inliers <= n_in
    if expanded:  # guided matching over the wider set at the seed pose
        wide_fs, wide_p = guide.wide_set()
        wide_p = np.asarray(wide_p, float)
        wide_known = np.flatnonzero(np.all(np.isfinite(wide_p), axis=1))
        q_cams, q_xy = np.asarray(query.camera_index, np.int64), normalised_xy(query, undistort)
        iq, il = match_by_projection(T_WS, q_cams, q_xy, query.descriptors, wide_p[wide_known],
                                     wide_fs.descriptors[wide_known], T_SC, focal_px, guide.radius_px, max_hamming)
        io, m, cams = wide_known[il], len(iq), q_cams[iq]
        if m < 6:
            return PnpResult(False, "guided matching found too few matches", m, 0, T_WS)
        xy, p_W = q_xy[iq], wide_p[io]
        T_WS, inliers = _refine(T_WS, p_W, xy, T_SC[cams], focal_px[cams], ransac_px, sigma_px)
        n_in = int(inliers.sum())
    if n_in < min_inliers or n_in < min_inlier_ratio * m:
        return PnpResult(False, f"{n_in} inliers of {m} matches", m, n_in, T_WS, expanded=expanded)
    r, J, _ = _residuals_jacobian(T_WS, p_W[inliers], xy[inliers], T_SC[cams][inliers])
    w = (focal_px[cams][inliers] / sigma_px)[:, None, None]
    Jw = (J * w).reshape(-1, 6)
    info = Jw.T @ Jw
    try:
        cov = np.linalg.inv(info) * cov_inflation
    except np.linalg.LinAlgError:
        return PnpResult(False, "degenerate inlier geometry", m, n_in, T_WS, expanded=expanded)
    return PnpResult(True, "accepted", m, n_in, T_WS, 0.5 * (cov + cov.T), iq[inliers], io[inliers], expanded)
