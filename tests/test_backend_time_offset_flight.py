"""The estimator finds a synthetic rig's camera-IMU time offset (backend.estimate_time_offset) over a 20 s simulated
flight, with the frontend's correction fed back (e2e tier: a few seconds of CPU)."""
import numpy as np
import pytest

from test_backend_time_offset import _agile

pytestmark = pytest.mark.e2e


def test_the_estimator_finds_the_offset_of_a_synthetic_rig_with_the_frontend_correction_fed_back():
    """Images 5 ms late against the IMU on a rig turning fast about every axis; observations moved by -td_est x
    their image velocity as the frontend does (between consecutive frames); the estimate ends within 1 ms and the
    trajectory's second half beats the one that ignores the offset."""
    import vio_sim as sim

    from services.backend.config import BackendConfig
    from services.backend.window.estimator import WindowedVioEstimator
    from shared.vio.cameras import VioCamera

    def run(estimate: bool, td=0.005, t0=0.5, t_end=20.0, rate=20.0):
        rng = np.random.default_rng(4)
        tr, pts, cams = _agile(), sim.landmarks_cylinder(300, seed=2), sim.rig(2)
        est = WindowedVioEstimator(BackendConfig(estimate_time_offset=estimate),
                                   [VioCamera(c.T_SC, c.undistort, c.K[0, 0]) for c in cams])
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
