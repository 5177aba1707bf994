"""Online camera-IMU time offset: the rotation residual of states placed late against the gyro, the filter's
convergence when the correction is fed back (the estimator on a synthetic flight: test_backend_time_offset_flight.py)."""
import numpy as np
import pytest

from services.backend.window.time_offset import TimeOffsetEstimator, rotation_residual
from shared.geometry import so3_log

pytestmark = pytest.mark.unit


def _agile():
    """A vio_sim trajectory that turns fast about every axis (angular rates up to ~2 rad/s)."""
    import vio_sim as sim

    return sim.Trajectory(e_amp=np.array([[0.3, 0.0], [0.3, 0.0], [0.6, 0.0]]),
                          e_freq=np.array([[1.2, 1.0], [1.0, 1.0], [0.5, 1.0]]))


def test_rotation_residual_of_states_placed_late_is_the_offset_times_the_rate_change():
    tr, td, b = _agile(), 0.004, np.array([0.01, -0.02, 0.005])
    t0, t1, hz = 3.75, 4.0, 1000.0
    ts = np.arange(t0, t1 + 1e-9, 1 / hz)
    R = tr.rotation(ts)  # body rates: finite differences of the trajectory's rotation, in the body frame
    omega = np.array([so3_log(R[k].T @ R[k + 1]) * hz for k in range(len(ts) - 1)])
    segments = [(1 / hz, w + b) for w in omega]  # a biased gyro, the bias known
    R0, R1 = tr.rotation(np.array([t0 + td, t1 + td]))
    w0, w1 = omega[0] + b, omega[-1] + b
    e, g = rotation_residual(R0, R1, segments, b, w0, w1)
    assert np.linalg.norm(g) > 0.1  # the rate changed
    np.testing.assert_allclose(e, td * g, atol=0.03 * td * np.linalg.norm(g))
    e0, _ = rotation_residual(*tr.rotation(np.array([t0, t1])), segments, b, w0, w1)
    assert np.linalg.norm(e0) < 0.02 * td * np.linalg.norm(g)  # no offset: the gyro agrees


def test_fed_back_correction_converges_when_the_window_absorbs_most_of_the_offset():
    """Each keyframe sees only 30 % of what is left of the offset (the rest is shared with the IMU) plus noise; the
    frontend's correction follows the estimate; the filter still ends at the true offset. A still rate says nothing;
    the estimate is clamped."""
    rng = np.random.default_rng(2)
    td, est = -0.006, TimeOffsetEstimator(sigma_s=0.01, walk_s=1e-4, max_abs_s=0.05)
    for _ in range(60):
        g = rng.normal(0, 0.1, 3)
        e = 0.3 * (td - est.td) * g + rng.normal(0, 1e-4, 3)
        est.update(e, g, sigma=1e-4)
    assert est.td == pytest.approx(td, abs=3e-4)
    before = est.td
    assert est.update(np.ones(3) * 1e-3, np.zeros(3), 1e-4) is None and est.td == before
    est_clamped = TimeOffsetEstimator(sigma_s=1.0, walk_s=0, max_abs_s=0.002)
    est_clamped.update(0.01 * g, g, 1e-4)
    assert est_clamped.td == 0.002
