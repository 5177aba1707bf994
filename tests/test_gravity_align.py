"""Gravity alignment of a moving start's window (services/backend/window/gravity_align.py) on a procedural flight."""

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import B, L, V, X

import vio_sim as sim
from services.backend.config import BackendConfig
from services.backend.window.gravity_align import align_window, imu_deltas
from shared.vio.imu_factors import ImuBuffer, make_params
from shared.geometry import so3_exp

T_SC = np.eye(4)
T_SC[:3, 3] = [0.05, -0.02, 0.01]
GYRO_BIAS = np.array([0.03, -0.05, 0.07])  # EuRoC-sized gyro biases (rad/s)


def _up_error_deg(T, T_gt):
    up, up_gt = T[:3, :3].T @ [0, 0, 1.0], T_gt[:3, :3].T @ [0, 0, 1.0]
    return float(np.degrees(np.arccos(np.clip(up @ up_gt, -1, 1))))


def _window(tilt: np.ndarray, acc_bias: np.ndarray, gyro_bias_error: np.ndarray = np.zeros(3), motion: float = 1.0):
    """Keyframes every 0.2 s over 1.2 s of an accelerating, turning flight: values at the ground truth turned by
    ``tilt`` about the first position (as a wrongly tilted W would hold them), the window's bias estimate
    (``acc_bias``, the true gyro bias + ``gyro_bias_error``), and the exact pre-integrations between keyframes
    (integrated at a zero bias, as a moving start's first window has them)."""
    tr = sim.Trajectory(scale=motion)
    if motion == 0.0:  # standing, tilted: the attitude of a drone on uneven ground
        tr.e_amp = np.zeros((3, 2))
        tr.yaw_rate = 0.0
    times = 3.0 + 0.2 * np.arange(7)
    st, om, ac = sim.imu(tr, 2.9, times[-1] + 0.1, 400.0)
    om = om + GYRO_BIAS
    buf = ImuBuffer()
    for s, w, a in zip(st, om, ac):
        buf.add(int(s), w, a)
    params = make_params(BackendConfig())
    pims = [buf.preintegrate(params, gtsam.imuBias.ConstantBias(), int(round(t0 * 1e9)), int(round(t1 * 1e9)))
            for t0, t1 in zip(times[:-1], times[1:])]
    gt = tr.T_WS(times)
    R = so3_exp(tilt)
    pivot = gt[0][:3, 3]
    values = gtsam.Values()
    for k, (T, v) in enumerate(zip(gt, tr.velocity(times))):
        Tw = np.eye(4)
        Tw[:3, :3], Tw[:3, 3] = R @ T[:3, :3], pivot + R @ (T[:3, 3] - pivot)
        values.insert(X(k), gtsam.Pose3(Tw))
        values.insert(V(k), R @ v + 0.3)  # velocities off too: the alignment replaces them
        values.insert(B(k), gtsam.imuBias.ConstantBias(acc_bias, GYRO_BIAS + gyro_bias_error))
    landmark = pivot + np.array([2.0, 1.0, 0.5])
    values.insert(L(3), R @ (landmark - pivot) + pivot)
    return values, pims, gt, tr.velocity(times), landmark


def test_imu_deltas_at_another_bias_match_an_integration_at_that_bias():
    """gtsam's first-order bias correction, gravity removed: what the window's bias would have integrated."""
    tr = sim.Trajectory()
    st, om, ac = sim.imu(tr, 0.0, 0.5, 400.0)
    buf = ImuBuffer()
    for s, w, a in zip(st, om + GYRO_BIAS, ac):
        buf.add(int(s), w, a)
    params = make_params(BackendConfig())
    at_zero = buf.preintegrate(params, gtsam.imuBias.ConstantBias(), 100_000_000, 300_000_000)
    exact = buf.preintegrate(params, gtsam.imuBias.ConstantBias(np.zeros(3), GYRO_BIAS), 100_000_000, 300_000_000)
    dR, dp, dv, dt = imu_deltas(at_zero, gtsam.imuBias.ConstantBias(np.zeros(3), GYRO_BIAS), 9.81)
    assert dt == pytest.approx(0.2)
    np.testing.assert_allclose(dR, exact.deltaRij().matrix(), atol=2e-4)
    np.testing.assert_allclose(dp, exact.deltaPij(), atol=2e-4)
    np.testing.assert_allclose(dv, exact.deltaVij(), atol=2e-3)


@pytest.mark.parametrize("tilt_deg", [3.0, 7.0])
def test_a_tilted_window_is_turned_back_to_gravity(tilt_deg):
    """A window held 3-7 deg off gravity with an accelerometer bias that absorbed the tilt: turned back to within
    0.1 deg, velocities the true ones, yaw and the first position kept, landmarks moved with the window (their
    position relative to every camera unchanged), the accelerometer bias reset, the gyro bias kept."""
    tilt = np.radians(tilt_deg) * np.array([0.6, -0.8, 0.0])
    values, pims, gt, v_gt, landmark = _window(tilt, acc_bias=np.array([0.5, -0.9, 0.1]))
    got = align_window(values, list(range(7)), pims, T_SC, 9.81, max_scale_error=0.1)
    assert got is not None
    out, info = got
    assert info.rotation_deg == pytest.approx(tilt_deg, abs=0.1) and info.scale == pytest.approx(1.0, abs=1e-3)
    for k in range(7):
        T = out.atPose3(X(k)).matrix()
        assert _up_error_deg(T, gt[k]) < 0.1
        np.testing.assert_allclose(out.atVector(V(k)), v_gt[k], atol=0.02)
        b = out.atConstantBias(B(k))
        np.testing.assert_allclose(b.accelerometer(), 0.0)
        np.testing.assert_allclose(b.gyroscope(), GYRO_BIAS)
        # the landmark in this body's frame is where it was before the turn
        before = np.linalg.solve(values.atPose3(X(k)).matrix(), np.r_[values.atPoint3(L(3)), 1.0])
        after = np.linalg.solve(T, np.r_[out.atPoint3(L(3)), 1.0])
        np.testing.assert_allclose(after, before, atol=1e-9)
    np.testing.assert_allclose(out.atPose3(X(0)).translation(), gt[0][:3, 3], atol=1e-12)
    # yaw kept: the first body's forward axis, projected on the ground, points the same way as before
    fwd = lambda T: T[:2, 0] / np.linalg.norm(T[:2, 0])  # noqa: E731
    assert np.degrees(np.arccos(fwd(out.atPose3(X(0)).matrix()) @ fwd(values.atPose3(X(0)).matrix()))) < 0.5


def test_an_inconsistent_window_is_refused():
    """Positions that do not fit the IMU (scaled by 1.3, as a window whose vision went wrong): no turn."""
    values, pims, _, _, _ = _window(np.zeros(3), np.zeros(3))
    p0 = values.atPose3(X(0)).translation()
    for k in range(7):
        T = values.atPose3(X(k)).matrix()
        T[:3, 3] = p0 + 1.3 * (T[:3, 3] - p0)
        values.update(X(k), gtsam.Pose3(T))
    assert align_window(values, list(range(7)), pims, T_SC, 9.81, max_scale_error=0.1) is None


def test_a_window_that_stands_still_is_aligned_with_its_scale_held():
    """A stereo window that barely moved (a drone on the ground with its rotors running fails the static test):
    the free scale is undetermined, so below min_travel_m it is held at 1 and gravity still comes out."""
    values, pims, gt, _, _ = _window(np.radians(2.0) * np.array([1.0, 0.0, 0.0]), np.zeros(3), motion=0.0)
    assert align_window(values, list(range(7)), pims, T_SC, 9.81, max_scale_error=0.1) is None  # scale free
    out, info = align_window(values, list(range(7)), pims, T_SC, 9.81, max_scale_error=0.1, min_travel_m=0.2)
    assert info.scale == 1.0 and info.rotation_deg == pytest.approx(2.0, abs=0.05)
    assert max(_up_error_deg(out.atPose3(X(k)).matrix(), gt[k]) for k in range(7)) < 0.05
