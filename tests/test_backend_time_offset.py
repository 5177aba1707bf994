"""Online camera-IMU time offset: the rotation residual of states placed late against the gyro, the filter's
convergence when the correction is fed back, and the estimator finding a synthetic rig's offset."""
import numpy as np
import pytest

from services.backend.time_offset import TimeOffsetEstimator, rotation_residual
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


def test_the_estimator_finds_the_offset_of_a_synthetic_rig_with_the_frontend_correction_fed_back():
    """Images 5 ms late against the IMU on a rig turning fast about every axis; observations moved by -td_est x
    their image velocity as the frontend does (between consecutive frames); the estimate ends within 1 ms and the
    trajectory's second half beats the one that ignores the offset."""
    import vio_sim as sim

    from services.backend.config import BackendConfig
    from services.backend.estimator import BackendCamera, WindowedVioEstimator

    def run(estimate: bool, td=0.005, t0=0.5, t_end=20.0, rate=20.0):
        rng = np.random.default_rng(4)
        tr, pts, cams = _agile(), sim.landmarks_cylinder(300, seed=2), sim.rig(2)
        est = WindowedVioEstimator(BackendConfig(estimate_time_offset=estimate),
                                   [BackendCamera(c.T_SC, c.undistort, c.K[0, 0]) for c in cams])
        st, om, ac = sim.imu(tr, 0.0, t_end + 0.1, 200.0, rng, gyro_nd=1.7e-4, acc_nd=2e-3, gyro_rw=1.9e-5,
                             acc_rw=3e-3)
        T0 = tr.T_WS(np.array([t0]))[0]
        est.initialise(int(round(t0 * 1e9)), T0[:3, :3], tr.velocity(np.array([t0]))[0], np.zeros(3), np.zeros(3),
                       static=True, p_W=T0[:3, 3])
        errors, j, prev = [], 0, None
        for i, t in enumerate(np.arange(t0, t_end, 1.0 / rate)):
            stamp = int(round(t * 1e9))
            while j < len(st) and st[j] <= stamp:
                est.add_imu(st[j], om[j], ac[j])
                j += 1
            T_late = tr.T_WS(np.array([t + td]))[0]  # what the image stamped t shows
            ids, c, uv = sim.observe(T_late, pts, cams, 0.5, rng, 25)
            clean = dict(zip(zip(*sim.observe(T_late, pts, cams)[:2]), sim.observe(T_late, pts, cams)[2]))
            vel = np.array([(clean[k] - prev[k]) * rate if prev and k in prev else (0.0, 0.0)
                            for k in zip(ids, c)]).reshape(-1, 2)
            prev = clean
            td_est = est.time_offset.td if estimate else 0.0
            res = est.process_frame(stamp, ids, c, uv - td_est * vel, is_keyframe=(i % 4 == 0))
            errors.append(np.linalg.norm(res.T_WS[:3, 3] - tr.T_WS(np.array([t]))[0][:3, 3]))
        return np.sqrt(np.mean(np.square(errors[len(errors) // 2:]))), est

    rmse_off, est_off = run(False)
    rmse_on, est_on = run(True)
    assert est_off.time_offset is None
    assert est_on.time_offset.updates > 20
    assert est_on.time_offset.td == pytest.approx(0.005, abs=1e-3)
    assert rmse_on < rmse_off
