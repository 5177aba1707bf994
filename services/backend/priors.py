"""Prior factors on the oldest state of the estimator's window: at initialisation, after the monocular rebuild
(services/backend/mono_init.py) and, as a Gaussian on (pose, velocity, bias), after each marginalisation."""

from __future__ import annotations

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X

# when the window's marginals could not give the next keyframe's covariance: loose, in the order
# (rotation [rad^2], position [m^2], velocity [m^2/s^2], accelerometer bias, gyro bias)
FALLBACK_COVARIANCE = np.diag([1e-2] * 3 + [1e-1] * 3 + [1.0] * 3 + [1e-2] * 3 + [1e-4] * 3)


def state_priors(n: int, T_WS: gtsam.Pose3, v_W: np.ndarray, bias: gtsam.imuBias.ConstantBias,
                 pose_sigmas: np.ndarray, vel_sigma: float, bias_sigmas: np.ndarray) -> list[gtsam.NonlinearFactor]:
    """Independent priors on X(n) (sigmas: rotation [rad] then position [m]), V(n) [m/s] and B(n) (accelerometer
    then gyro)."""
    return [gtsam.PriorFactorPose3(X(n), T_WS, gtsam.noiseModel.Diagonal.Sigmas(pose_sigmas)),
            gtsam.PriorFactorVector(V(n), v_W, gtsam.noiseModel.Isotropic.Sigma(3, vel_sigma)),
            gtsam.PriorFactorConstantBias(B(n), bias, gtsam.noiseModel.Diagonal.Sigmas(bias_sigmas))]


def marginal_prior(values: gtsam.Values, n: int, cov: np.ndarray | None) -> gtsam.NonlinearFactor:
    """The joint 15x15 marginal ``cov`` of state n's (pose, velocity, bias) as a Gaussian prior linearised at its
    estimate in ``values`` (:data:`FALLBACK_COVARIANCE` when None or not finite)."""
    lin = gtsam.Values()
    lin.insert(X(n), values.atPose3(X(n)))
    lin.insert(V(n), values.atVector(V(n)))
    lin.insert(B(n), values.atConstantBias(B(n)))
    if cov is None or not np.all(np.isfinite(cov)):
        cov = FALLBACK_COVARIANCE
    info = np.linalg.inv(0.5 * (cov + cov.T))
    R = np.linalg.cholesky(0.5 * (info + info.T)).T  # R^T R = information
    jf = gtsam.JacobianFactor(X(n), R[:, 0:6], V(n), R[:, 6:9], B(n), R[:, 9:15], np.zeros(15),
                              gtsam.noiseModel.Unit.Create(15))
    return gtsam.LinearContainerFactor(jf, lin)
