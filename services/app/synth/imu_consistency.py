"""How well a smooth trajectory and a recorded IMU describe the same motion, and the spline fit that makes them agree.

A replica renders its images along a :class:`services.app.synth.trajectory.Trajectory` fitted to the ground truth and, with
``imu='real'``, ships the recorded imu0 beside them. On the real rig the images and the IMU see one motion; on a
replica they agree only as well as the fitted trajectory follows the motion the IMU felt. Two measures, each on the
residual between the recorded samples and what the trajectory predicts, after a running mean over
``bias_window_s`` is taken out (the slowly varying bias and what the fit cannot see):

- rotation: the gyro residual integrated over ``window_s`` (50 ms, one camera frame at 20 Hz), RMS angle [deg];
- position: the accelerometer residual integrated twice over ``window_s`` (0.25 s, a few keyframes), RMS [mm].

A white-noise IMU alone would give ~0.002 deg and ~0.1 mm (EuRoC's imu0 densities). The ground truth's own noise
is the rest: a laser tracker's positions (EuRoC's machine hall) are far noisier than a motion-capture system's, so
a fit that follows them closely shakes the images by centimetres against the accelerometer. The knot spacings are
chosen per channel from a few candidates by these two measures (:func:`fit_to_imu`), and the coarse clock offset
found by correlating angular speeds (:func:`services.app.synth.imu_sim.time_offset`, 1 ms steps) is refined to 0.1 ms by the
gyro residual (:func:`refine_offset`). No estimator is involved: the choice rests on the IMU and the ground truth.

A spline of the ground truth cannot follow what the ground truth itself gets wrong: a motion-capture system that
loses markers in fast flight (V2_03's orientation is off the gyro by ~1 deg/s RMS between 0.3 and 5 Hz, 2-4 % of
the motion, against 0.1 deg/s on V1_02), a laser tracker's jitter. A real camera on the rig sees the motion the
IMU felt. :func:`follow_imu` therefore takes the fine motion from the IMU itself: above a cut-off the orientation
follows the gyro and the position the accelerometer, below it the ground truth (whose absolute pose is right where
the IMU's bias and double integration are not). What is left between images and IMU is then the IMU's own white
noise and vibration above the spline's reach, as on the real rig.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from scipy.integrate import cumulative_trapezoid
from scipy.signal import butter, sosfiltfilt

from shared.euroc import PoseSeries
from shared.geometry import R_to_quat_wxyz, so3_exp
from services.app.synth.imu_sim import G_W, ImuData
from services.app.synth.trajectory import Trajectory

ROTATION_KNOTS_S = (0.01, 0.02, 0.05, 0.1)
POSITION_KNOTS_S = (0.05, 0.1, 0.2, 0.3)
ROTATION_CUTOFF_HZ = 0.1  # above: the gyro (its bias drifts over minutes); below: the ground truth
POSITION_CUTOFF_HZ = 0.3  # above: the accelerometer, integrated twice; below: the ground truth


@dataclasses.dataclass(frozen=True)
class ImuFit:
    """The fit :func:`fit_to_imu` chose and how well it agrees with the IMU."""
    trajectory: Trajectory  # what the images follow: the spline, with the IMU's fine motion when followed
    spline: Trajectory  # the spline of the ground truth alone, at the chosen knot spacings
    offset_ns: int  # ground-truth stamps were moved by -offset_ns onto the IMU clock (on top of the coarse offset)
    gyro_mismatch_deg: float  # RMS rotation mismatch per 50 ms, of ``trajectory``
    accel_mismatch_mm: float  # RMS position mismatch per 0.25 s, of ``trajectory``
    spline_gyro_mismatch_deg: float  # the same of ``spline``
    spline_accel_mismatch_mm: float

    @property
    def rotation_knot_spacing_s(self) -> float:
        return self.spline.rotation_knot_spacing_s

    @property
    def position_knot_spacing_s(self) -> float:
        return self.spline.knot_spacing_s


def _inside(traj: Trajectory, imu: ImuData, margin_ns: int) -> np.ndarray:
    """Indices of the IMU samples at least ``margin_ns`` inside the trajectory's span."""
    return np.flatnonzero((imu.stamps_ns >= traj.t0_ns + margin_ns) & (imu.stamps_ns <= traj.t_end_ns - margin_ns))


def _window_rms(residual: np.ndarray, dt_s: float, window_s: float, bias_window_s: float, order: int) -> float:
    """RMS norm of ``residual`` (N, 3) integrated ``order`` times (1 or 2) over consecutive windows, after its running
    mean over ``bias_window_s`` is removed."""
    k = max(int(round(bias_window_s / dt_s)), 1)
    if len(residual) < 3 * k:
        raise ValueError(f"IMU consistency: {len(residual)} samples, need at least {3 * k} (3 bias windows)")
    kernel = np.ones(k) / k
    mean = np.stack([np.convolve(residual[:, i], kernel, mode="same") for i in range(3)], axis=1)
    r = (residual - mean)[k:-k]
    n = max(int(round(window_s / dt_s)), 1)
    r = r[: len(r) // n * n].reshape(-1, n, 3)
    if order == 1:
        err = r.sum(axis=1) * dt_s
    else:  # position after n steps with no velocity error at the window's start
        err = np.cumsum(r, axis=1).sum(axis=1) * dt_s ** 2
    return float(np.sqrt(np.mean(np.sum(err ** 2, axis=1))))


def _dt_s(imu: ImuData) -> float:
    return float(np.median(np.diff(imu.stamps_ns))) * 1e-9


def gyro_mismatch_deg(traj: Trajectory, imu: ImuData, offset_ns: int = 0, window_s: float = 0.05,
                      bias_window_s: float = 2.0, margin_ns: int = 10_000_000) -> float:
    """RMS angle [deg] between the recorded gyro and ``traj``'s body rate at ``t + offset_ns``, integrated over
    ``window_s``."""
    i = _inside(traj, imu, margin_ns + abs(int(offset_ns)))
    t = imu.stamps_ns[i]
    d = imu.omega_S[i] - traj.body_rate(t + int(offset_ns))
    return float(np.degrees(_window_rms(d, _dt_s(imu), window_s, bias_window_s, order=1)))


def accel_mismatch_mm(traj: Trajectory, imu: ImuData, window_s: float = 0.25, bias_window_s: float = 2.0,
                      margin_ns: int = 10_000_000) -> float:
    """RMS position [mm] that the recorded accelerometer's disagreement with ``traj`` builds up over ``window_s``."""
    i = _inside(traj, imu, margin_ns)
    t = imu.stamps_ns[i]
    pred = np.einsum("nji,nj->ni", traj.rotation(t), traj.acceleration(t) - G_W)
    return 1e3 * _window_rms(imu.acc_S[i] - pred, _dt_s(imu), window_s, bias_window_s, order=2)


def refine_offset(traj: Trajectory, imu: ImuData, half_range_ns: int = 1_500_000, step_ns: int = 100_000) -> int:
    """The offset d [ns] within +-``half_range_ns`` (``step_ns`` steps) at which the recorded gyro at t best matches
    ``traj``'s body rate at t + d."""
    offsets = np.arange(-half_range_ns, half_range_ns + 1, step_ns, dtype=np.int64)
    cost = [gyro_mismatch_deg(traj, imu, int(d), margin_ns=10_000_000 + half_range_ns) for d in offsets]
    return int(offsets[int(np.argmin(cost))])


def _highpass(x: np.ndarray, dt_s: float, cutoff_hz: float) -> np.ndarray:
    """Zero-phase high-pass of ``x`` (N, 3) along time (2nd-order Butterworth, run forwards and backwards). Each
    end is extended by five time constants of the mean of its first (last) second: scipy's own padding starts
    from the single end sample, whose noise then rings through seconds of the output."""
    sos = butter(2, cutoff_hz, btype="highpass", fs=1.0 / dt_s, output="sos")
    n_pad = int(np.ceil(5.0 / (cutoff_hz * dt_s)))
    m = max(1, min(len(x), int(round(1.0 / dt_s))))
    padded = np.concatenate([np.repeat(x[:m].mean(axis=0, keepdims=True), n_pad, axis=0), x,
                             np.repeat(x[-m:].mean(axis=0, keepdims=True), n_pad, axis=0)])
    return sosfiltfilt(sos, padded, axis=0, padtype=None)[n_pad:n_pad + len(x)]


def _integrate(x: np.ndarray, dt_s: float) -> np.ndarray:
    """Trapezoidal running integral of ``x`` (N, 3) along time, zero at the first sample."""
    return cumulative_trapezoid(x, dx=dt_s, axis=0, initial=0.0)


def follow_imu(traj: Trajectory, imu: ImuData, rotation_cutoff_hz: float = ROTATION_CUTOFF_HZ,
               position_cutoff_hz: float = POSITION_CUTOFF_HZ, margin_ns: int = 10_000_000) -> Trajectory:
    """``traj`` with the IMU's fine motion, sampled at the IMU stamps inside ``traj`` and fitted again (knots every
    two samples).

    Orientation: R = Exp(phi) R_traj with phi in W. To first order its body rate is omega_traj + R_traj^T dphi/dt
    (a perturbation on the left has no cross term with the large omega_traj, one on the right does), so
    dphi/dt = R_traj h, h the gyro's residual against ``traj`` high-passed in S (the bias is constant in S, not in
    W), and phi is its integral, high-passed again. Position: p = p_traj + the high-passed double integral of the
    accelerometer's residual against ``traj`` (with the corrected orientation), high-passed in S and then in W."""
    if rotation_cutoff_hz <= 0 or position_cutoff_hz <= 0:
        raise ValueError("follow_imu: the cut-off frequencies must be positive")
    i = _inside(traj, imu, margin_ns)
    t = imu.stamps_ns[i]
    if len(t) < 100:
        raise ValueError(f"follow_imu: {len(t)} IMU samples inside the trajectory, need at least 100")
    dt = _dt_s(imu)
    R_traj = traj.rotation(t)
    h = _highpass(imu.omega_S[i] - traj.body_rate(t), dt, rotation_cutoff_hz)
    phi = _highpass(_integrate(np.einsum("nij,nj->ni", R_traj, h), dt), dt, rotation_cutoff_hz)
    R = so3_exp(phi) @ R_traj
    # the accelerometer's residual against traj, in S (where its bias is constant), then in W
    r_acc = imu.acc_S[i] - np.einsum("nji,nj->ni", R, traj.acceleration(t) - G_W)
    e = _highpass(np.einsum("nij,nj->ni", R, _highpass(r_acc, dt, position_cutoff_hz)), dt, position_cutoff_hz)
    dp = _highpass(_integrate(_highpass(_integrate(e, dt), dt, position_cutoff_hz), dt), dt, position_cutoff_hz)
    return Trajectory(PoseSeries(t, traj.position(t) + dp, R_to_quat_wxyz(R)), knot_spacing_s=2 * dt)


def fit_to_imu(gt: PoseSeries, imu: ImuData, rotation_knots_s=ROTATION_KNOTS_S,
               position_knots_s=POSITION_KNOTS_S, follow: bool = True) -> ImuFit:
    """Fit ``gt`` (already on the IMU clock to ~1 ms) so that it agrees best with ``imu``: the rotation knot spacing
    with the least gyro mismatch, then the clock offset refined to 0.1 ms, then the position knot spacing with the
    least accelerometer mismatch; then, with ``follow``, the IMU's fine motion on top (:func:`follow_imu`)."""
    if not rotation_knots_s or not position_knots_s:
        raise ValueError("fit_to_imu: give at least one candidate knot spacing per channel")
    p0 = position_knots_s[0]
    rot = min(rotation_knots_s, key=lambda s: gyro_mismatch_deg(Trajectory(gt, p0, s), imu))
    offset = refine_offset(Trajectory(gt, p0, rot), imu)
    gt = dataclasses.replace(gt, stamps_ns=gt.stamps_ns - offset)
    fits = {s: Trajectory(gt, s, rot) for s in position_knots_s}
    mismatch = {s: accel_mismatch_mm(tr, imu) for s, tr in fits.items()}
    pos = min(mismatch, key=mismatch.get)
    spline_gyro = gyro_mismatch_deg(fits[pos], imu)
    if not follow:
        return ImuFit(fits[pos], fits[pos], offset, spline_gyro, mismatch[pos], spline_gyro, mismatch[pos])
    traj = follow_imu(fits[pos], imu)
    return ImuFit(traj, fits[pos], offset, gyro_mismatch_deg(traj, imu), accel_mismatch_mm(traj, imu), spline_gyro,
                  mismatch[pos])
