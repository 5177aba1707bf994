"""Online refinement of the cameras' extrinsics T_SC in the window estimator (``backend.refine_extrinsics``).

Each camera c gets a Pose3 variable E(c) = T_SC in the window graph; its reprojection factors become
``ProjectionFactorPPP`` (body pose, extrinsic, landmark: gtsam_unstable) instead of a factor with the extrinsic fixed.
The calibration file's T_SC is the first prior on E(c), with sigmas from the config (how much the user trusts the
calibration). When the oldest keyframe leaves the window, the joint marginal of the next keyframe's state and every
E(c) becomes one prior (services/backend/priors.py: the correlations matter, since a camera's pose X E(c) is known
far better than X or E(c) alone). Each E(c) block is then widened (:func:`carried_covariance`): the window's marginal
also counts the observations still in it, and each observation takes part in about as many marginalisations as the
window has keyframes, so only that share of the information gained is kept, plus a small random walk per keyframe
that lets the estimate follow a camera mount that really moves.

What is observable: the cameras' rotation (the gyro against the images) and their positions relative to each other
(stereo) settle within seconds; their common position relative to the IMU only through rotational motion (the lever
arm), much more slowly: its sigma (``WindowedVioEstimator.extrinsic_covariance``) says how well it is known.
"""

from __future__ import annotations

import gtsam
import numpy as np


def extrinsic_key(camera: int) -> int:
    """gtsam key of camera ``camera``'s extrinsic T_SC (symbol 'e')."""
    return gtsam.symbol("e", int(camera))


def prior_sigmas(rot_rad: float, trans_m: float) -> np.ndarray:
    """(6,) Pose3 tangent sigmas: rotation [rad] three times, then translation [m] three times."""
    return np.r_[[float(rot_rad)] * 3, [float(trans_m)] * 3]


def extrinsic_priors(T_SC: np.ndarray, covariances: np.ndarray) -> list[gtsam.NonlinearFactor]:
    """One prior per camera on E(c) at ``T_SC[c]`` (C,4,4) with covariance ``covariances[c]`` (C,6,6), Pose3 tangent
    order (rotation, translation) at that estimate."""
    out = []
    for c, (T, cov) in enumerate(zip(np.asarray(T_SC, float), np.asarray(covariances, float))):
        noise = gtsam.noiseModel.Gaussian.Covariance(0.5 * (cov + cov.T))
        out.append(gtsam.PriorFactorPose3(extrinsic_key(c), gtsam.Pose3(T), noise))
    return out


def carried_covariance(marginal: np.ndarray | None, previous: np.ndarray, walk_sigmas: np.ndarray,
                       share: float) -> np.ndarray:
    """E(c)'s next prior covariance (6,6). The window's ``marginal`` holds the prior's information plus that of every
    observation in the window; each observation stays in the window for about 1/``share`` keyframes, so only
    ``share`` of the gain is kept each time (an observation ends up counted about once); then the random walk of one
    keyframe (``walk_sigmas`` (6,)) is added. ``previous`` plus the walk when the marginal is missing or not
    finite."""
    walk = np.diag(np.asarray(walk_sigmas, float) ** 2)
    prev = np.asarray(previous, float)
    if marginal is None or not np.all(np.isfinite(marginal)):
        return prev + walk
    info_prev, info_marg = np.linalg.inv(prev), np.linalg.inv(0.5 * (marginal + marginal.T))
    w, U = np.linalg.eigh(0.5 * ((info_marg - info_prev) + (info_marg - info_prev).T))
    gain = (U * np.clip(w, 0.0, None)) @ U.T  # only what the window added (numerically never negative)
    return np.linalg.inv(info_prev + float(share) * gain) + walk
