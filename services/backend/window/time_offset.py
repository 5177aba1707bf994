"""Online camera-IMU time offset (``backend.estimate_time_offset``): an image stamped t was taken at IMU time t + td.

The window's states follow their images (many landmarks, sub-pixel), so with an offset each keyframe's orientation
is where the body was td later than its stamp, while the IMU factors between them integrate the gyro over the
stamps. The rotation between two keyframes then differs from the gyro's by how much the angular rate changed in
between, times td (:func:`rotation_residual`): ``e = td * g``. After each keyframe's optimisation
:meth:`TimeOffsetEstimator.update` regresses the newest interval's e on g, ``delta = e . g / g . g``, and folds delta
into a scalar Kalman filter (measurement variance ``sigma^2 / g . g``, a random walk per keyframe). The frontend moves
every published track by ``-td_est`` times its image velocity (pixels per second between its last two frames), so
the window's images come at their stamps and what is left is ``(td - td_est) g``; the window shares some of it with
the IMU, so each step sees part of what is left, and the filter settles where e and g no longer correlate: the true
offset. The offset is observable only while the angular rate changes; steady motion leaves it where it is.

(Reprojection residuals against the image velocity are no use for this: the window moves its states along the
trajectory by td and leaves the images nothing to say; measured on a synthetic rig.)
"""
from __future__ import annotations

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, X

from shared.vio.imu_factors import ImuBuffer
from shared.geometry import so3_exp, so3_log


def rotation_residual(R_W0: np.ndarray, R_W1: np.ndarray, segments, gyro_bias: np.ndarray, omega0: np.ndarray,
                      omega1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(e (3,), g (3,)) of two states' rotations ``R_W0``, ``R_W1`` (as the window's images place them) against the gyro
    integrated between their stamps (``segments``: (dt [s], mean omega [rad/s], ...) pieces, ImuBuffer.segments):
    ``e = Log(dR^T R_W0^T R_W1)`` and ``g = omega1 - dR^T omega0`` (bias removed; rad, rad/s). States placed td late
    give ``e = td g`` to first order: the gyro's rotation over [t0 + td, t1 + td] differs from that over [t0, t1] by
    how much the rate changed."""
    b = np.asarray(gyro_bias, float)
    dR = np.eye(3)
    for dt, w, *_ in segments:
        dR = dR @ so3_exp(dt * (np.asarray(w, float) - b))
    e = so3_log(dR.T @ R_W0.T @ R_W1)
    return e, (np.asarray(omega1, float) - b) - dR.T @ (np.asarray(omega0, float) - b)


def interval_residual(values: gtsam.Values, imu: ImuBuffer, stamps: dict[int, int], k: int, n: int
                      ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`rotation_residual` of the window's states k -> n at the current estimate, the gyro bias of n removed."""
    t0, t1 = stamps[k], stamps[n]
    b_g = np.asarray(values.atConstantBias(B(n)).gyroscope())
    return rotation_residual(values.atPose3(X(k)).rotation().matrix(), values.atPose3(X(n)).rotation().matrix(),
                             imu.segments(t0, t1), b_g, imu.omega_at(t0), imu.omega_at(t1))


class TimeOffsetEstimator:
    """Scalar Kalman filter of the offset td [s] fed with residual regressions (see the module's docstring)."""

    def __init__(self, sigma_s: float, walk_s: float, max_abs_s: float, min_flow: float = 1e-5) -> None:
        self.td = 0.0
        self.var = sigma_s ** 2
        self.walk_var = walk_s ** 2
        self.max_abs_s = max_abs_s
        self.min_flow = min_flow  # g . g below this: the rate hardly changed, nothing to say [rad^2/s^2]
        self.updates = 0

    def update(self, residual: np.ndarray, rate_change: np.ndarray, sigma: float) -> float | None:
        """Fold one interval's rotation residual e (3,) [rad] and rate change g (3,) [rad/s] (:func:`rotation_residual`)
        with the noise ``sigma`` [rad] of e into the estimate; returns the measured delta [s], None when the rate
        hardly changed."""
        r, v = np.asarray(residual, float).ravel(), np.asarray(rate_change, float).ravel()
        self.var += self.walk_var
        info = float(np.sum(v * v))
        if info < self.min_flow:
            return None
        delta = float(np.sum(r * v)) / info
        meas_var = sigma ** 2 / info
        gain = self.var / (self.var + meas_var)
        self.td = float(np.clip(self.td + gain * delta, -self.max_abs_s, self.max_abs_s))
        self.var *= 1.0 - gain
        self.updates += 1
        return delta
