"""IMU pre-integration against the analytic ground truth of a procedural trajectory."""

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import B, V, X

import vio_sim as sim
from services.backend.config import BackendConfig
from shared.vio.imu_factors import ImuBuffer, ImuDataError, imu_factor, make_bias, make_params, predict


def _state(tr, t):
    return tr.T_WS(np.array([t]))[0], tr.velocity(np.array([t]))[0]


@pytest.mark.parametrize("bias", [(np.zeros(3), np.zeros(3)), (np.array([0.01, -0.02, 0.005]), np.array([0.1, 0.05, -0.2]))])
def test_preintegration_reproduces_ground_truth_relative_motion(bias):
    bg, ba = bias
    tr = sim.Trajectory()
    st, om, ac = sim.imu(tr, 0.0, 2.0, 200.0)
    buf = ImuBuffer()
    buf.add_many(st, om + bg, ac + ba)
    t0, t1 = 0.503, 1.0  # start between two samples
    params = make_params(BackendConfig())
    pim = buf.preintegrate(params, make_bias(bg, ba), int(t0 * 1e9), int(t1 * 1e9))
    T0, v0 = _state(tr, t0)
    T1, v1 = _state(tr, t1)
    T_pred, v_pred = predict(pim, T0, v0, make_bias(bg, ba))
    assert np.linalg.norm(T_pred[:3, 3] - T1[:3, 3]) < 1e-5  # 0.5 s at 200 Hz (midpoint integration)
    assert np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(T_pred[:3, :3].T @ T1[:3, :3]))) < 1e-4
    assert np.linalg.norm(v_pred - v1) < 1e-4

    # the factor is (almost) satisfied by the ground-truth states, and not by a perturbed one
    f = imu_factor(pim, (X(0), V(0), B(0)), (X(1), V(1), B(1)))
    vals = gtsam.Values()
    vals.insert(X(0), gtsam.Pose3(T0))
    vals.insert(V(0), v0)
    vals.insert(B(0), make_bias(bg, ba))
    vals.insert(X(1), gtsam.Pose3(T1))
    vals.insert(V(1), v1)
    vals.insert(B(1), make_bias(bg, ba))
    e_gt = f.error(vals)
    T1_bad = T1.copy()
    T1_bad[:3, 3] += [0.02, 0, 0]
    vals.update(X(1), gtsam.Pose3(T1_bad))
    assert e_gt < 0.05 and f.error(vals) > 100 * max(e_gt, 1e-3)


def test_buffer_rejects_bad_samples_and_uncovered_intervals():
    buf = ImuBuffer()
    assert buf.add(10, np.zeros(3), np.zeros(3))
    assert not buf.add(10, np.zeros(3), np.zeros(3))  # duplicate stamp
    assert not buf.add(20, np.array([np.nan, 0, 0]), np.zeros(3))
    assert buf.dropped == 2
    with pytest.raises(ImuDataError, match="do not cover"):
        buf.segments(0, 5)
    with pytest.raises(ImuDataError, match="empty"):
        buf.segments(10, 10)
