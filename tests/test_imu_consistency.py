"""services/app/synth/imu_consistency.py: the measures of agreement between a trajectory and an IMU, the sub-ms clock offset, and
the per-channel knot choice, on a procedural flight whose IMU is simulated from the true motion."""

import dataclasses

import numpy as np
import pytest

from shared.euroc import PoseSeries
from services.app.synth.imu_consistency import accel_mismatch_mm, fit_to_imu, follow_imu, gyro_mismatch_deg, refine_offset
from services.app.synth.imu_sim import ImuNoise, simulate_imu
from services.app.synth.trajectory import Trajectory, _qmul

RATE_NS = 5_000_000  # 200 Hz, as EuRoC's imu0 and ground truth


def _shaky_flight(duration_s: float = 16.0) -> Trajectory:
    """A slow loop with a drone's quick wobble: yaw and roll oscillating at 1.5 and 2.3 Hz (up to ~3 rad/s)."""
    t = np.arange(0.0, duration_s + 1e-9, 0.005)
    stamps = 1_000_000_000 + np.round(t * 1e9).astype(np.int64)
    p = np.column_stack([np.sin(0.4 * t), 0.5 * np.sin(0.8 * t), 1.0 + 0.05 * np.sin(2 * np.pi * 1.1 * t)])
    yaw, roll = 0.3 * np.sin(2 * np.pi * 1.5 * t), 0.2 * np.sin(2 * np.pi * 2.3 * t)
    qz = np.column_stack([np.cos(yaw / 2), 0 * t, 0 * t, np.sin(yaw / 2)])
    qx = np.column_stack([np.cos(roll / 2), np.sin(roll / 2), 0 * t, 0 * t])
    return Trajectory(PoseSeries(stamps, p, _qmul(qz, qx)), knot_spacing_s=0.02)


@pytest.fixture(scope="module")
def flight():
    """(true trajectory, its 200 Hz samples as a ground truth, an IMU with EuRoC's noise simulated from it)."""
    truth = _shaky_flight()
    stamps = np.arange(truth.t0_ns, truth.t_end_ns + 1, RATE_NS, dtype=np.int64)
    gt = PoseSeries(stamps, truth.position(stamps), truth.quaternion_wxyz(stamps))
    imu = simulate_imu(truth, stamps[40:-40], ImuNoise(), seed=4)
    return truth, gt, imu


def test_the_true_motion_agrees_with_its_imu_to_the_noise_floor(flight):
    truth, _, imu = flight
    # white noise alone: 1.7e-4 rad/s/sqrt(Hz) over 50 ms ~ 0.002 deg; 2e-3 m/s^2/sqrt(Hz) over 0.25 s ~ 0.1 mm
    assert gyro_mismatch_deg(truth, imu) < 0.006
    assert accel_mismatch_mm(truth, imu) < 0.3


def test_a_late_clock_or_a_shaking_fit_shows_in_the_measures(flight):
    truth, gt, imu = flight
    assert gyro_mismatch_deg(truth, imu, offset_ns=2_000_000) > 5 * gyro_mismatch_deg(truth, imu)
    rng = np.random.default_rng(1)
    noisy = dataclasses.replace(gt, p_WS=gt.p_WS + rng.normal(scale=0.003, size=gt.p_WS.shape))  # 3 mm per sample
    assert accel_mismatch_mm(Trajectory(noisy, 0.02), imu) > 5 * accel_mismatch_mm(truth, imu)


@pytest.mark.parametrize("offset_ns", [-1_200_000, 700_000])
def test_refine_offset_finds_a_sub_millisecond_offset(flight, offset_ns):
    truth, _, imu = flight
    # the IMU stamps its sample of time t as t - offset: the gyro at stamp s matches the body rate at s + offset
    late = dataclasses.replace(imu, stamps_ns=imu.stamps_ns - offset_ns)
    assert abs(refine_offset(truth, late) - offset_ns) <= 100_000


def test_fit_to_imu_smooths_noisy_positions_and_keeps_clean_orientations(flight):
    truth, gt, imu = flight
    rng = np.random.default_rng(2)
    noisy = dataclasses.replace(gt, p_WS=gt.p_WS + rng.normal(scale=0.003, size=gt.p_WS.shape))
    fit = fit_to_imu(noisy, imu, rotation_knots_s=(0.02, 0.3), position_knots_s=(0.02, 0.2))
    assert fit.position_knot_spacing_s == pytest.approx(0.2) and fit.rotation_knot_spacing_s == pytest.approx(0.02)
    assert fit.offset_ns == 0
    assert fit.accel_mismatch_mm == pytest.approx(accel_mismatch_mm(fit.trajectory, imu))
    assert fit.accel_mismatch_mm < accel_mismatch_mm(Trajectory(noisy, 0.02, 0.02), imu) / 3
    # the fit's positions stay on the true ones (smoothing, not a different path)
    t = imu.stamps_ns[100:-100]
    assert np.sqrt(np.mean(np.sum((fit.trajectory.position(t) - truth.position(t)) ** 2, axis=1))) < 2e-3
    with pytest.raises(ValueError, match="at least one candidate"):
        fit_to_imu(noisy, imu, rotation_knots_s=())


def _rotation_error_deg(a: Trajectory, b: Trajectory, t: np.ndarray) -> np.ndarray:
    from shared.geometry import so3_log
    return np.degrees(np.linalg.norm(so3_log(np.einsum("nji,njk->nik", a.rotation(t), b.rotation(t))), axis=1))


def test_follow_imu_takes_the_fine_motion_the_ground_truth_got_wrong_from_the_imu(flight):
    truth, gt, imu = flight
    # a motion-capture ground truth that wobbles where the body did not: 0.3 deg at 1.3 Hz and 0.2 deg at 3.1 Hz
    # about changing axes, and 2 mm of slow jitter in position (what a lost marker or a laser tracker does)
    s = (gt.stamps_ns - gt.stamps_ns[0]) * 1e-9
    wobble = np.radians(np.column_stack([0.3 * np.sin(2 * np.pi * 1.3 * s), 0.2 * np.sin(2 * np.pi * 3.1 * s + 1),
                                         0.25 * np.sin(2 * np.pi * 0.7 * s + 2)]))
    from shared.geometry import R_to_quat_wxyz, so3_exp
    q = R_to_quat_wxyz(truth.rotation(gt.stamps_ns) @ so3_exp(wobble))
    dp = 0.002 * np.column_stack([np.sin(2 * np.pi * 0.9 * s), np.sin(2 * np.pi * 1.7 * s + 1), np.sin(2 * np.pi * 2.3 * s)])
    bad = dataclasses.replace(gt, p_WS=gt.p_WS + dp, q_WS_wxyz=q)
    spline = fit_to_imu(bad, imu, rotation_knots_s=(0.01,), position_knots_s=(0.05,), follow=False)
    fit = fit_to_imu(bad, imu, rotation_knots_s=(0.01,), position_knots_s=(0.05,))
    assert fit.spline_gyro_mismatch_deg == pytest.approx(spline.gyro_mismatch_deg)
    assert fit.gyro_mismatch_deg < spline.gyro_mismatch_deg / 5
    assert fit.accel_mismatch_mm < spline.accel_mismatch_mm / 5
    t = imu.stamps_ns[400:-400]  # 2 s inside the ends, where the zero-phase filters have settled
    rot_before, rot_after = _rotation_error_deg(spline.trajectory, truth, t), _rotation_error_deg(fit.trajectory, truth, t)
    assert np.sqrt(np.mean(rot_after ** 2)) < np.sqrt(np.mean(rot_before ** 2)) / 5
    pos_before = np.linalg.norm(spline.trajectory.position(t) - truth.position(t), axis=1)
    pos_after = np.linalg.norm(fit.trajectory.position(t) - truth.position(t), axis=1)
    assert np.sqrt(np.mean(pos_after ** 2)) < np.sqrt(np.mean(pos_before ** 2)) / 3


def test_follow_imu_keeps_an_exact_ground_truth_whatever_the_imu_biases(flight):
    truth, gt, imu = flight
    biased = dataclasses.replace(imu, omega_S=imu.omega_S + [0.05, -0.03, 0.08], acc_S=imu.acc_S + [0.2, -0.1, 0.15])
    followed = follow_imu(truth, biased)
    t = imu.stamps_ns[400:-400]
    assert _rotation_error_deg(followed, truth, t).max() < 0.05
    # the accelerometer's white noise, integrated twice above 0.3 Hz, moves the position by ~1 mm
    assert np.linalg.norm(followed.position(t) - truth.position(t), axis=1).max() < 2e-3
    assert gyro_mismatch_deg(followed, biased) < 0.006 and accel_mismatch_mm(followed, biased) < 0.3
    with pytest.raises(ValueError, match="cut-off"):
        follow_imu(truth, imu, rotation_cutoff_hz=0.0)
    with pytest.raises(ValueError, match="at least 100"):
        follow_imu(truth, dataclasses.replace(imu, stamps_ns=imu.stamps_ns[:50], omega_S=imu.omega_S[:50],
                                              acc_S=imu.acc_S[:50]))
