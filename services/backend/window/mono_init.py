"""Visual-inertial bootstrap of a monocular window that started moving.

With one camera and a moving start the window's poses come from the IMU alone, with an unknown initial
velocity and a rough gravity direction: they drift too fast for any landmark to pass the triangulation
checks, so vision never gets a hold. Once the oldest and the newest keyframe of the window see enough
shared features with enough parallax, this module rebuilds the window from vision and the IMU:

1. two-view geometry of the oldest (a) and newest (b) keyframe (essential matrix, RANSAC) gives their
   relative pose up to scale and the shared points in camera a;
2. every other keyframe is placed against those points by PnP (same unknown scale);
3. a linear least-squares problem in the keyframe velocities, gravity and the metric scale (the
   pre-integrated IMU deltas between consecutive keyframes, as in VINS-Mono's visual-inertial alignment)
   fixes the scale; a second solve with gravity held at its known magnitude refines it;
4. the window's poses and velocities are replaced (yaw and the oldest position kept), its prior is reset
   at the oldest keyframe, and landmarks are triangulated again from the new poses.
"""

from __future__ import annotations

import cv2
import gtsam
import numpy as np
from gtsam.symbol_shorthand import V, X

from services.backend.window.init import rotation_aligning
from services.backend.window.triangulation import triangulate


def two_view(xy_a: np.ndarray, xy_b: np.ndarray, ransac_rad: float) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(R_ba, unit t_ba, inlier mask) with x_b ~ R_ba x_a + t_ba from normalised coordinates (N,2); None if
    the essential matrix cannot be estimated."""
    if len(xy_a) < 8:
        return None
    E, mask = cv2.findEssentialMat(xy_a, xy_b, np.eye(3), cv2.RANSAC, 0.999, ransac_rad)
    if E is None or E.shape != (3, 3):
        return None
    _, R, t, mask = cv2.recoverPose(E, xy_a, xy_b, np.eye(3), mask=mask)
    return R, t.ravel() / max(np.linalg.norm(t), 1e-12), mask.ravel() > 0


def align(R_0S: np.ndarray, c_0: np.ndarray, t_SC: np.ndarray, dp: np.ndarray, dv: np.ndarray, dt: np.ndarray,
          gravity: float, scale: float | None = None) -> tuple[float, np.ndarray, np.ndarray] | None:
    """Metric scale s, velocities (K,3) and gravity (3,) in the frame of the first camera, from up-to-scale
    camera centres ``c_0`` (K,3), body rotations ``R_0S`` (K,3,3), lever arm ``t_SC`` and the IMU deltas of
    consecutive keyframes ``dp``, ``dv`` (K-1,3) (in the earlier body frame), ``dt`` (K-1,) [s].

    Body position p_k = s c_k - R_0S_k t_SC; p_k+1 = p_k + v_k dt + g dt^2 / 2 + R_k dp_k;
    v_k+1 = v_k + g dt + R_k dv_k. Solved once freely, then with |g| = ``gravity`` (direction of the first
    solve). ``scale`` given (metric centres: a stereo window): s is that, not solved for (a window that barely
    moved does not tell it). None when the solution is implausible (negative scale, |g| far from ``gravity``)."""
    K = len(c_0)
    lever = R_0S @ t_SC  # (K,3)
    free = scale is None  # the unknowns: K velocities, then s if free, then g if not fixed

    def solve(g_fixed: np.ndarray | None):
        n = 3 * K + int(free) + (3 if g_fixed is None else 0)
        gcol = 3 * K + int(free)
        rows, rhs = [], []
        for k in range(K - 1):
            R, h = R_0S[k], dt[k]
            A = np.zeros((3, n))
            A[:, 3 * k:3 * k + 3] = -h * np.eye(3)
            b = R @ dp[k] + lever[k + 1] - lever[k]
            if free:
                A[:, 3 * K] = c_0[k + 1] - c_0[k]
            else:
                b = b - scale * (c_0[k + 1] - c_0[k])
            if g_fixed is None:
                A[:, gcol:] = -0.5 * h * h * np.eye(3)
            else:
                b = b + 0.5 * h * h * g_fixed
            rows.append(A)
            rhs.append(b)
            A = np.zeros((3, n))
            A[:, 3 * (k + 1):3 * k + 6] = np.eye(3)
            A[:, 3 * k:3 * k + 3] = -np.eye(3)
            b = R @ dv[k]
            if g_fixed is None:
                A[:, gcol:] = -h * np.eye(3)
            else:
                b = b + h * g_fixed
            rows.append(A)
            rhs.append(b)
        x = np.linalg.lstsq(np.concatenate(rows), np.concatenate(rhs), rcond=None)[0]
        return x, (float(x[3 * K]) if free else float(scale))

    if K < 4:
        return None
    x, s = solve(None)
    g = x[3 * K + int(free):]
    if not 0.8 * gravity < np.linalg.norm(g) < 1.2 * gravity or s <= 0:
        return None
    g = g / np.linalg.norm(g) * gravity
    x, s = solve(g)
    if s <= 0:
        return None
    return s, x[:3 * K].reshape(K, 3), g


def bootstrap(est, n: int, min_features: int, min_parallax_rad: float, ransac_px: float) -> str:
    """Rebuild the window of ``est`` (a WindowedVioEstimator with one camera) from vision and IMU, the newest
    state ``n`` (a keyframe about to join) included. '' when done, else why not (the estimator unchanged)."""
    states = list(est.keyframes) + ([n] if n != est.keyframes[-1] else [])
    if len(states) < 4:
        return "fewer than 4 keyframes"
    b = states[-1]
    f_px = float(est.focal_px[0])
    obs_b = {lm: o[0][1] for lm, o in est.observations_of(b).items()}
    for i in range(len(states) - 3):  # the oldest keyframe that still shares enough features with the newest
        a = states[i]
        obs_a = {lm: o[0][1] for lm, o in est.observations_of(a).items()}
        common = sorted(set(obs_a) & set(obs_b))
        if len(common) >= min_features:
            states = states[i:]
            break
    else:
        return "too few shared features"
    xy_a = np.array([obs_a[lm] for lm in common])
    xy_b = np.array([obs_b[lm] for lm in common])
    tv = two_view(xy_a, xy_b, ransac_px / f_px)
    if tv is None:
        return "no essential matrix"
    R_ba, t_ba, inl = tv
    fa = np.c_[xy_a, np.ones(len(xy_a))] @ R_ba.T
    fb = np.c_[xy_b, np.ones(len(xy_b))]
    cos = np.sum(fa * fb, 1) / np.linalg.norm(fa, axis=1) / np.linalg.norm(fb, axis=1)
    if inl.sum() < min_features or np.median(np.arccos(np.clip(cos[inl], -1, 1))) < min_parallax_rad:
        return "too little parallax"
    T_ba = np.eye(4)
    T_ba[:3, :3], T_ba[:3, 3] = R_ba, t_ba
    pts = {}
    for lm, x0, x1, ok in zip(common, xy_a, xy_b, inl):
        if ok:
            p = triangulate(np.stack([np.eye(4), T_ba]), np.stack([x0, x1]))
            if np.all(np.isfinite(p)) and p[2] > 0 and (T_ba[:3, :3] @ p + T_ba[:3, 3])[2] > 0:
                pts[lm] = p
    if len(pts) < min_features:
        return "too few two-view points"
    T_CkCa = {a: np.eye(4), b: T_ba}
    for s in states[1:-1]:  # the keyframes in between: PnP against the two-view points
        obs_s = est.observations_of(s)
        lms = [lm for lm in pts if lm in obs_s]
        if len(lms) < 8:
            return "too few points for PnP"
        P = np.array([pts[lm] for lm in lms])
        xy = np.array([obs_s[lm][0][1] for lm in lms])
        ok, rvec, tvec, _ = cv2.solvePnPRansac(P, xy, np.eye(3), None, reprojectionError=ransac_px / f_px,
                                               iterationsCount=100, flags=cv2.SOLVEPNP_EPNP)
        if not ok:
            return "PnP failed"
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
        T_CkCa[s] = T
    T_SC = est.T_SC[0]
    T_CaC = [np.linalg.inv(T_CkCa[s]) for s in states]
    R_0S = np.array([T[:3, :3] @ T_SC[:3, :3].T for T in T_CaC])
    c_0 = np.array([T[:3, 3] for T in T_CaC])
    pims = [est.imu_factor_to(s).preintegratedMeasurements() for s in states[1:]]
    res = align(R_0S, c_0, T_SC[:3, 3], np.array([p.deltaPij() for p in pims]), np.array([p.deltaVij() for p in pims]),
                np.array([p.deltaTij() for p in pims]), est.cfg.gravity_m_s2)
    if res is None:
        return "implausible scale or gravity"
    scale, v_0, g_0 = res
    # world frame: gravity of the alignment along -z, yaw and position of the oldest keyframe kept
    T_WSa = est.values.atPose3(X(a)).matrix()
    R_WCa = T_WSa[:3, :3] @ T_SC[:3, :3]
    R_WCa = rotation_aligning(R_WCa @ g_0, [0.0, 0.0, -1.0]) @ R_WCa
    p0 = scale * c_0[0] - R_0S[0] @ T_SC[:3, 3]
    for k, s in enumerate(states):
        T = np.eye(4)
        T[:3, :3] = R_WCa @ R_0S[k]
        T[:3, 3] = T_WSa[:3, 3] + R_WCa @ (scale * c_0[k] - R_0S[k] @ T_SC[:3, 3] - p0)
        est.values.update(X(s), gtsam.Pose3(T))
        est.values.update(V(s), R_WCa @ v_0[k])
    c = est.cfg
    est.reset_prior(a, c.prior_sigma_tilt_moving_rad, 0.1, c.prior_sigma_gyro_bias)
    est.forget_triangulations()  # triangulated from the drifting poses: start again
    return ""


def metric_hold(est) -> bool:
    """Whether the window of ``est`` (a WindowedVioEstimator) has a metric scale: with two or more cameras once
    initialised; with one camera once it stood still or :func:`bootstrap` rebuilt it (before that its poses come
    from the IMU alone, with an unknown initial velocity, and anything placed with them has no scale)."""
    return bool(est.initialised) and not est.mono_pending
