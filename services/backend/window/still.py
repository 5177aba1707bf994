"""Standing-still detection and its factors, for a monocular rig.

With one camera a landmark needs parallax from the rig's own motion before it can be triangulated, so while
the rig stands still (a drone on the ground with its rotors running, a pause mid-flight) vision gives the
window nothing and the IMU alone lets the pose drift within seconds. The image says more than that,
though: when the tracked features have not moved since the last keyframe, neither has the camera.

:func:`still_motion` compares a frame's feature positions with those of the last keyframe: when the median
displacement stays below a few tenths of a pixel (raw image motion, so both rotation and translation are
small) the rig counts as still, and the relative rotation is measured from the bearings (Kabsch). The
estimator then adds :func:`still_factors`: a relative-pose factor keyframe -> frame with that rotation and
zero translation, and a zero-velocity prior on the frame. Through the IMU factor this makes roll, pitch
and the biases observable while nothing can be triangulated, so that the motion starts from a good state.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import V, X


@dataclass(frozen=True)
class StillMotion:
    """A frame found standing still relative to its keyframe."""

    R_SkSn: np.ndarray  # (3,3) body rotation of the frame in the keyframe's body frame, measured from bearings
    median_flow_px: float  # median feature displacement since the keyframe [px]
    num_features: int  # features shared with the keyframe


def bearing_rotation(f_a: np.ndarray, f_b: np.ndarray) -> np.ndarray:
    """Rotation R minimising sum |f_b - R f_a|^2 over unit bearings (N,3) (Kabsch)."""
    U, _, Vt = np.linalg.svd(np.asarray(f_a, float).T @ np.asarray(f_b, float))
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T


def _unit(xy: np.ndarray) -> np.ndarray:
    f = np.c_[xy, np.ones(len(xy))]
    return f / np.linalg.norm(f, axis=1, keepdims=True)


def still_motion(xy_kf: np.ndarray, xy_now: np.ndarray, focal_px: float, R_SC: np.ndarray, max_flow_px: float,
                 min_features: int) -> StillMotion | None:
    """StillMotion when the median displacement of the shared features (normalised coordinates (N,2) of one
    camera in the keyframe and now) is below ``max_flow_px`` and there are at least ``min_features``; else None."""
    if len(xy_kf) < max(min_features, 3) or max_flow_px <= 0:
        return None
    flow = float(np.median(np.linalg.norm(np.asarray(xy_now) - np.asarray(xy_kf), axis=1)) * focal_px)
    if flow >= max_flow_px:
        return None
    R_CnCk = bearing_rotation(_unit(xy_kf), _unit(xy_now))  # f_now = R_CnCk f_kf
    R_SkSn = R_SC @ R_CnCk.T @ R_SC.T
    return StillMotion(R_SkSn, flow, len(xy_kf))


def still_factors(k: int, n: int, still: StillMotion, sigma_rot_rad: float, sigma_pos_m: float,
                  sigma_vel_m_s: float) -> list[gtsam.NonlinearFactor]:
    """Relative pose keyframe k -> state n (measured rotation, zero translation) and zero velocity at n."""
    T = np.eye(4)
    T[:3, :3] = still.R_SkSn
    sig = np.array([sigma_rot_rad] * 3 + [sigma_pos_m] * 3)
    return [gtsam.BetweenFactorPose3(X(k), X(n), gtsam.Pose3(T), gtsam.noiseModel.Diagonal.Sigmas(sig)),
            gtsam.PriorFactorVector(V(n), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, sigma_vel_m_s))]


def _in_first_camera(observations) -> np.ndarray | None:
    """A landmark's normalised xy in camera 0 among one state's observations [(camera, xy)], or None."""
    return next((xy for c, xy in observations if c == 0), None)


def mono_frame_factors(obs: dict, k: int, n: int, focal_px: float, R_SC: np.ndarray, cfg,
                       waiting_for_hold: bool) -> tuple[list[gtsam.NonlinearFactor], bool]:
    """One camera (or the first camera of a rig, ``backend.still_stereo``): the factors state n gets against
    keyframe k, and whether it stands still.

    ``obs``: the estimator's landmark -> state -> [(camera, normalised xy)]. Standing still: the relative pose
    and zero velocity of :func:`still_factors`. Moving while the window has no metric hold yet
    (``waiting_for_hold``, a moving start): a weak zero-velocity prior of ``cfg.mono_init_speed_sigma_m_s``.
    ``cfg``: the back end's config (``mono_still_*``, ``mono_init_speed_sigma_m_s``)."""
    if cfg.mono_still_flow_px <= 0:
        return [], False
    shared = [(a, b) for by_state in obs.values() if k in by_state and n in by_state
              and (a := _in_first_camera(by_state[k])) is not None and (b := _in_first_camera(by_state[n])) is not None]
    xy = np.reshape(shared, (-1, 2, 2))
    still = still_motion(xy[:, 0], xy[:, 1], focal_px, R_SC, cfg.mono_still_flow_px, cfg.mono_still_min_features)
    if still is not None:
        return still_factors(k, n, still, cfg.mono_still_sigma_rot_rad, cfg.mono_still_sigma_pos_m,
                             cfg.mono_still_sigma_vel_m_s), True
    if waiting_for_hold and cfg.mono_init_speed_sigma_m_s > 0:
        return [gtsam.PriorFactorVector(V(n), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(
            3, cfg.mono_init_speed_sigma_m_s))], False
    return [], False
