"""Online refinement of the cameras' extrinsics T_SC in the window estimator (``backend.refine_extrinsics``).

Each camera c gets a Pose3 variable E(c) = T_SC in the window graph; its reprojection factors become
``ProjectionFactorPPP`` (body pose, extrinsic, landmark: gtsam_unstable) instead of a factor with the extrinsic fixed.
The calibration file's T_SC is the first prior on E(c), with sigmas from the config (how much the user trusts the
calibration). When the oldest keyframe leaves the window, the joint marginal of the next keyframe's state and every
E(c) becomes one prior (services/backend/window/priors.py: the correlations matter, since a camera's pose X E(c) is known
far better than X or E(c) alone), each E(c) block widened by a small random walk per keyframe
(:func:`carried_covariance`). The marginal also counts the observations still in the window, as the state's prior
does: alone that would make the prior ever more confident, since an extrinsic never changes; the walk bounds it,
and lets the estimate follow a camera mount that really moves. (Keeping only each keyframe's share of the
information instead, so that an observation counts about once, left the cameras' positions 2.4-3.1 mm off over the
second half of a run, where this keeps them within 1.9-2.4 mm: docs/estimator.md.)

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


def carried_covariance(marginal: np.ndarray | None, previous: np.ndarray, walk_sigmas: np.ndarray) -> np.ndarray:
    """E(c)'s next prior covariance (6,6): the window's ``marginal`` plus the random walk of one keyframe
    (``walk_sigmas`` (6,)); ``previous`` plus the walk when the marginal is missing or not finite."""
    base = previous if marginal is None or not np.all(np.isfinite(marginal)) else 0.5 * (marginal + marginal.T)
    return np.asarray(base, float) + np.diag(np.asarray(walk_sigmas, float) ** 2)


class ExtrinsicRefinement:
    """The window's extrinsic variables E(c) (``cfg``: BackendConfig, for ``num_cameras`` cameras): their keys, the
    prior factors they have outside the joint marginal prior, and each one's carried covariance (rotation [rad],
    translation [m])."""

    def __init__(self, cfg, num_cameras: int) -> None:
        self.keys = tuple(extrinsic_key(c) for c in range(num_cameras))
        first = np.diag(prior_sigmas(np.deg2rad(cfg.extrinsic_prior_sigma_rot_deg), cfg.extrinsic_prior_sigma_trans_m))
        self.covariance = np.array([first ** 2] * num_cameras)
        self._walk = prior_sigmas(np.deg2rad(cfg.extrinsic_walk_rot_deg), cfg.extrinsic_walk_trans_m)
        self.priors: list[gtsam.NonlinearFactor] = []

    def start(self, values: gtsam.Values, T_SC: np.ndarray) -> None:
        """E(c) at ``T_SC`` (C,4,4) into ``values`` (unless there) with the calibration's priors."""
        for key, T in zip(self.keys, np.asarray(T_SC, float)):
            if not values.exists(key):
                values.insert(key, gtsam.Pose3(T))
        self.priors = extrinsic_priors(T_SC, self.covariance)

    def read(self, values: gtsam.Values) -> np.ndarray:
        """(C,4,4) the extrinsics' estimate in ``values``."""
        return np.array([values.atPose3(key).matrix() for key in self.keys])

    def carry_apart(self, T_SC: np.ndarray) -> None:
        """No joint marginal this time: each extrinsic keeps its prior (at ``T_SC``), widened by the walk."""
        self.covariance = np.array([carried_covariance(None, prev, self._walk) for prev in self.covariance])
        self.priors = extrinsic_priors(T_SC, self.covariance)

    def carry_joint(self, joint: np.ndarray) -> np.ndarray:
        """The joint marginal (15 + 6C square: the oldest state, then the extrinsics in key order) with each
        extrinsic's block widened by the walk (still positive definite), for one prior over all of them; the
        separate priors are dropped."""
        joint = np.array(joint, float)
        for c in range(len(self.keys)):
            b = slice(15 + 6 * c, 21 + 6 * c)
            self.covariance[c] = carried_covariance(joint[b, b], self.covariance[c], self._walk)
            joint[b, b] = self.covariance[c]
        self.priors = []
        return joint
