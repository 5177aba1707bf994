"""IMU pre-integration for the back end (gtsam ``CombinedImuFactor``).

Noise model: the config holds *continuous-time* densities (white noise sigma_c [unit/sqrt(Hz)], bias
random walk sigma_rw [unit/s/sqrt(Hz)]). gtsam's pre-integration takes exactly these squared as
"covariances" and discretises internally: white noise of a sample spaced dt becomes sigma_c^2 / dt
(``PreintegrationBase::integrateMeasurement``), the bias random walk over an interval Delta t of the factor
becomes sigma_rw^2 * Delta t (``CombinedImuFactor``). So no discretisation is done here.

Integration: between consecutive samples the mean of the two readings is held over the interval
(trapezoid), the acceleration taken at the interval's mid attitude; the interval is clipped to [t0, t1] with linear interpolation of the readings at the ends, so
a frame time that falls between two IMU samples is handled exactly to first order.
"""

from __future__ import annotations

import bisect
import gtsam
import numpy as np

from shared.vio.config import VioConfig

NS = 1e-9


class ImuDataError(ValueError):
    """IMU samples that cannot be integrated (out of order, missing over an interval, non-finite)."""


def make_params(cfg: VioConfig, gyro_noise_density: float | None = None, accel_noise_density: float | None = None,
                gyro_random_walk: float | None = None, accel_random_walk: float | None = None
                ) -> gtsam.PreintegrationCombinedParams:
    """Pre-integration parameters for gravity -g along z of W (``MakeSharedU``) with continuous noise densities.

    Densities default to the config's; pass an ``ImuCalib``'s values to use the sensor's own.
    """
    sg = cfg.gyro_noise_density if gyro_noise_density is None else gyro_noise_density
    sa = cfg.accel_noise_density if accel_noise_density is None else accel_noise_density
    rg = cfg.gyro_random_walk if gyro_random_walk is None else gyro_random_walk
    ra = cfg.accel_random_walk if accel_random_walk is None else accel_random_walk
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(cfg.gravity_m_s2)
    eye = np.eye(3)
    p.setGyroscopeCovariance(sg ** 2 * eye)
    p.setAccelerometerCovariance(sa ** 2 * eye)
    p.setIntegrationCovariance(cfg.integration_sigma ** 2 * eye)
    p.setBiasOmegaCovariance(rg ** 2 * eye)
    p.setBiasAccCovariance(ra ** 2 * eye)
    return p


def make_bias(gyro_bias: np.ndarray, acc_bias: np.ndarray) -> gtsam.imuBias.ConstantBias:
    return gtsam.imuBias.ConstantBias(np.asarray(acc_bias, float), np.asarray(gyro_bias, float))


class ImuBuffer:
    """Time-ordered IMU samples; integrates any interval [t0, t1] covered by samples."""

    def __init__(self) -> None:
        self.stamps_ns: list[int] = []
        self.omega: list[np.ndarray] = []
        self.acc: list[np.ndarray] = []
        self.dropped = 0

    def add(self, stamp_ns: int, omega_S: np.ndarray, acc_S: np.ndarray) -> bool:
        """Append one sample; out-of-order, duplicate or non-finite samples are dropped (counted), returns False."""
        omega_S = np.asarray(omega_S, float).reshape(3)
        acc_S = np.asarray(acc_S, float).reshape(3)
        if (self.stamps_ns and stamp_ns <= self.stamps_ns[-1]) or not (np.all(np.isfinite(omega_S))
                                                                        and np.all(np.isfinite(acc_S))):
            self.dropped += 1
            return False
        self.stamps_ns.append(int(stamp_ns))
        self.omega.append(omega_S)
        self.acc.append(acc_S)
        return True

    def add_many(self, stamps_ns: np.ndarray, omega_S: np.ndarray, acc_S: np.ndarray) -> None:
        for t, w, a in zip(stamps_ns, omega_S, acc_S):
            self.add(int(t), w, a)

    def __len__(self) -> int:
        return len(self.stamps_ns)

    def covers(self, t0_ns: int, t1_ns: int) -> bool:
        return bool(self.stamps_ns) and self.stamps_ns[0] <= t0_ns and self.stamps_ns[-1] >= t1_ns

    def prune_before(self, t_ns: int) -> None:
        """Forget samples older than the last sample at or before ``t_ns`` (that one is kept for interpolation)."""
        i = bisect.bisect_right(self.stamps_ns, t_ns) - 1
        if i > 0:
            del self.stamps_ns[:i], self.omega[:i], self.acc[:i]

    def omega_at(self, t_ns: int) -> np.ndarray:
        """The gyro reading at ``t_ns`` [rad/s] (interpolated; the nearest sample outside the buffer)."""
        return np.asarray(self._at(t_ns)[0], float)

    def _at(self, t_ns: int) -> tuple[np.ndarray, np.ndarray]:
        i = bisect.bisect_right(self.stamps_ns, t_ns) - 1
        i = min(max(i, 0), len(self.stamps_ns) - 1)
        if i + 1 >= len(self.stamps_ns) or t_ns <= self.stamps_ns[i]:
            return self.omega[i], self.acc[i]
        a = (t_ns - self.stamps_ns[i]) / (self.stamps_ns[i + 1] - self.stamps_ns[i])
        return ((1 - a) * self.omega[i] + a * self.omega[i + 1], (1 - a) * self.acc[i] + a * self.acc[i + 1])

    def segments(self, t0_ns: int, t1_ns: int) -> list[tuple[float, np.ndarray, np.ndarray]]:
        """(dt [s], mean omega, mean acc) for each piece of [t0, t1] between samples."""
        if t1_ns <= t0_ns:
            raise ImuDataError(f"empty IMU interval [{t0_ns}, {t1_ns}] ns")
        if not self.stamps_ns:
            raise ImuDataError("no IMU samples buffered")
        # allow extrapolation by holding the last reading for at most 20 ms (a frame slightly after the last sample)
        if self.stamps_ns[0] > t0_ns or self.stamps_ns[-1] < t1_ns - 20_000_000:
            raise ImuDataError(f"IMU samples [{self.stamps_ns[0]}, {self.stamps_ns[-1]}] ns do not cover "
                               f"[{t0_ns}, {t1_ns}] ns")
        lo = bisect.bisect_right(self.stamps_ns, t0_ns)
        hi = bisect.bisect_left(self.stamps_ns, t1_ns)
        times = [t0_ns] + self.stamps_ns[lo:hi] + [t1_ns]
        out = []
        w_prev, a_prev = self._at(t0_ns)
        for ta, tb in zip(times[:-1], times[1:]):
            w_b, a_b = self._at(tb)
            if tb > ta:
                out.append(((tb - ta) * NS, 0.5 * (w_prev + w_b), 0.5 * (a_prev + a_b)))
            w_prev, a_prev = w_b, a_b
        return out

    def preintegrate(self, params: gtsam.PreintegrationCombinedParams, bias: gtsam.imuBias.ConstantBias,
                     t0_ns: int, t1_ns: int) -> gtsam.PreintegratedCombinedMeasurements:
        pim = gtsam.PreintegratedCombinedMeasurements(params, bias)
        self.integrate_into(pim, bias, t0_ns, t1_ns)
        return pim

    def integrate_into(self, pim: gtsam.PreintegratedCombinedMeasurements, bias: gtsam.imuBias.ConstantBias,
                       t0_ns: int, t1_ns: int) -> None:
        """Extend ``pim`` (integrated up to ``t0_ns`` with ``bias``) to ``t1_ns``. Split at a sample's stamp, two
        calls give the pre-integration of one (the pieces between samples are the same)."""
        bg, ba = np.asarray(bias.gyroscope()), np.asarray(bias.accelerometer())
        for dt, w, a in self.segments(t0_ns, t1_ns):
            # gtsam rotates the step's acceleration by the attitude at the step start; rotating it by half the
            # step's own rotation first makes the velocity update midpoint-accurate (second order in dt)
            a_mid = gtsam.Rot3.Expmap((w - bg) * (0.5 * dt)).rotate(a - ba) + ba  # gtsam subtracts ba again
            pim.integrateMeasurement(a_mid, w, dt)

    def last_stamp_at_or_before(self, t_ns: int) -> int | None:
        """Stamp of the newest sample at or before ``t_ns`` (None when there is none)."""
        i = bisect.bisect_right(self.stamps_ns, t_ns) - 1
        return self.stamps_ns[i] if i >= 0 else None


def predict(pim: gtsam.PreintegratedCombinedMeasurements, T_WS: np.ndarray, v_W: np.ndarray,
            bias: gtsam.imuBias.ConstantBias) -> tuple[np.ndarray, np.ndarray]:
    """State at the end of ``pim`` from (T_WS, v_W) at its start: returns (T_WS, v_W)."""
    nav = pim.predict(gtsam.NavState(gtsam.Pose3(T_WS), np.asarray(v_W, float)), bias)
    return nav.pose().matrix(), np.asarray(nav.velocity())


def imu_factor(pim: gtsam.PreintegratedCombinedMeasurements, keys_i: tuple[int, int, int],
               keys_j: tuple[int, int, int]) -> gtsam.CombinedImuFactor:
    """Factor between states i and j; ``keys_*`` = (pose, velocity, bias) keys."""
    (xi, vi, bi), (xj, vj, bj) = keys_i, keys_j
    return gtsam.CombinedImuFactor(xi, vi, xj, vj, bi, bj, pim)
