"""Online refinement of the cameras' extrinsics (backend.refine_extrinsics) on a synthetic rig with known truth:
a calibration perturbed by 1 deg / 1 cm per camera comes back, the trajectory with it; the carried prior;
the refined extrinsics reach the fast path and the frontend, and another rig's are refused."""

import numpy as np
import pytest

import vio_sim as sim
from services.backend.config import BackendConfig
from services.backend.window.estimator import WindowedVioEstimator
from shared.vio.cameras import VioCamera
from services.backend.window.extrinsics import carried_covariance
from shared.geometry import pose_error
from tools.vio.extrinsics_bench import perturb_extrinsics


GYRO_BIAS = np.array([0.002, -0.001, 0.003])
ACC_BIAS = np.array([0.05, -0.03, 0.02])


def _run(cams, T_SC_given, refine: bool, t_end=14.0, t0=0.5, rate=10.0, seed=1):
    """The estimator on a procedural trajectory, told the extrinsics ``T_SC_given``; (position errors, estimator)."""
    rng = np.random.default_rng(seed)
    tr = sim.Trajectory()
    pts = sim.landmarks_cylinder(300, seed=2)
    cfg = BackendConfig(refine_extrinsics=refine)
    est = WindowedVioEstimator(cfg, [VioCamera(T, c.undistort, c.K[0, 0]) for c, T in zip(cams, T_SC_given)])
    st, om, ac = sim.imu(tr, 0.0, t_end + 0.1, 200.0, rng, gyro_nd=1.7e-4, acc_nd=2e-3, gyro_rw=1.9e-5, acc_rw=3e-3,
                         gyro_bias=GYRO_BIAS, acc_bias=ACC_BIAS)
    T0 = tr.T_WS(np.array([t0]))[0]
    est.initialise(int(round(t0 * 1e9)), T0[:3, :3], tr.velocity(np.array([t0]))[0], np.zeros(3), np.zeros(3),
                   static=True, p_W=T0[:3, 3])
    times = np.arange(t0, t_end, 1.0 / rate)
    errors, j = [], 0
    for i, (t, T) in enumerate(zip(times, tr.T_WS(times))):
        stamp = int(round(t * 1e9))
        while j < len(st) and st[j] <= stamp:
            est.add_imu(st[j], om[j], ac[j])
            j += 1
        ids, c, uv = sim.observe(T, pts, cams, 0.5, rng, 25)
        res = est.process_frame(stamp, ids, c, uv, is_keyframe=(i % 2 == 0))
        errors.append(np.linalg.norm(res.T_WS[:3, 3] - T[:3, 3]))
    return np.array(errors), est, res


@pytest.mark.e2e  # several seconds of CPU: out of the unit tier (tests/README.md)
def test_a_perturbed_calibration_is_refined_back_to_the_true_one():
    cams = sim.rig(2)
    true = np.array([c.T_SC for c in cams])
    given = perturb_extrinsics(true, 1.0, 0.01, seed=3)
    t0, r0 = pose_error(given, true)
    assert np.allclose(np.degrees(r0), 1.0) and np.allclose(t0, 0.01)
    err_fixed, _, res_fixed = _run(cams, given, refine=False)
    err_refined, est, res = _run(cams, given, refine=True)
    err_true, _, _ = _run(cams, true, refine=False)
    assert res_fixed.T_SC is None  # without refinement nothing is reported
    t_err, r_err = pose_error(res.T_SC, true)
    assert np.all(np.degrees(r_err) < 0.2), np.degrees(r_err)  # the rotation: within seconds (gyro vs images)
    # the position relative to the IMU is seen only through the lever arm under rotation: in 14 s it is barely
    # known, and the estimator says so (its sigma); the error must stay within what it claims
    sig = np.sqrt(np.diagonal(est.extrinsic_covariance, axis1=1, axis2=2))
    assert np.all(t_err < 3.0 * np.linalg.norm(sig[:, 3:], axis=1)), (t_err, sig[:, 3:])
    assert np.all(t_err < 0.008), t_err  # and it did move towards the truth from 10 mm (4.4 / 2.7 mm here)
    np.testing.assert_allclose(est.T_SC, res.T_SC)  # what the estimator uses is what it reports
    late = slice(len(err_true) // 2, None)  # after the refinement settled
    rms = {k: float(np.sqrt(np.mean(e[late] ** 2))) for k, e in
           (("fixed", err_fixed), ("refined", err_refined), ("true", err_true))}
    assert rms["refined"] < 0.5 * rms["fixed"], rms
    assert rms["refined"] < 1.5 * rms["true"] + 0.005, rms
    # the carried prior tightened from the calibration's 2 deg / 2 cm: the rotation much, the position a little
    assert np.all(sig[:, :3] < np.deg2rad(0.5)) and np.all(sig[:, 3:] < 0.02)


def test_the_carried_prior_is_the_marginal_widened_by_the_walk():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(6, 6))
    marginal = A @ A.T * 1e-6
    prev = np.diag([1e-4] * 3 + [4e-4] * 3)
    walk = np.array([1e-4] * 3 + [1e-3] * 3)
    np.testing.assert_allclose(carried_covariance(marginal, prev, walk), marginal + np.diag(walk ** 2), rtol=1e-12)
    for bad in (None, np.full((6, 6), np.nan)):  # no marginals this time: the previous prior, widened
        np.testing.assert_allclose(carried_covariance(bad, prev, walk), prev + np.diag(walk ** 2))


def _window(T_SC):
    from shared.messages import EstimatorWindow, Header

    return EstimatorWindow(header=Header(stamp_ns=10), T_WS=np.eye(4), v_W=np.zeros(3), gyro_bias=np.zeros(3),
                           acc_bias=np.zeros(3), T_corr=np.eye(4), landmark_ids=np.zeros(0, np.int64),
                           p_W=np.zeros((0, 3)), T_SC=T_SC)


def test_the_fast_path_and_the_frontend_take_the_refined_extrinsics_and_refuse_another_rigs():
    """... and the frontend takes the time offset estimate from the same message."""
    from services.frontend.node import make_node
    from services.app.system_config import load_system_config
    from shared.camera import camera_from_sensor_yaml, camera_to_sensor_yaml
    from shared.codec import decode, encode
    from shared.dataflow import RejectedMessage
    from shared.rig import load_rig_config

    cfg = load_system_config(None, [])
    cams = []
    for c in load_rig_config(cfg.rig):  # the bundled rig at 1/8 size: the nodes' lookup tables build in no time
        y = camera_to_sensor_yaml(c)
        y["resolution"] = [w // 8 for w in y["resolution"]]
        y["intrinsics"] = [v / 8 for v in y["intrinsics"]]
        cams.append(camera_from_sensor_yaml(y, c.name))
    refined = perturb_extrinsics(np.array([c.T_SC for c in cams]), 0.5, 0.005, seed=1)
    msg = decode(encode(_window(refined)))  # the field survives the wire
    np.testing.assert_allclose(msg.T_SC, refined)
    fe = make_node(cfg, cams)  # tracker and fast path: both take the window
    odo = fe.fast_path
    fe.on_window(msg)
    np.testing.assert_allclose(odo.tracker.vision.T_SC, refined)
    np.testing.assert_allclose([c.T_SC for c in fe.tracker.cameras], refined)
    # a window without extrinsics (refinement off) changes nothing; one of another rig is refused, not applied
    odo.on_window(_window(np.zeros((0, 4, 4))))
    np.testing.assert_allclose(odo.tracker.vision.T_SC, refined)
    other = np.repeat(np.eye(4)[None], 3, axis=0)
    with pytest.raises(RejectedMessage):
        odo.on_window(_window(other))
    with pytest.raises(RejectedMessage):
        fe.on_window(_window(other))
    np.testing.assert_allclose(odo.tracker.vision.T_SC, refined)
    np.testing.assert_allclose([c.T_SC for c in fe.tracker.cameras], refined)
    # the camera-IMU time offset (backend.estimate_time_offset) travels in the same message to the frontend
    import dataclasses

    timed = decode(encode(dataclasses.replace(_window(np.zeros((0, 4, 4))), time_offset_s=0.003)))
    assert timed.time_offset_s == 0.003
    fe.on_window(dataclasses.replace(timed, status="initialising"))  # no state yet: nothing to take
    assert fe.tracker.time_offset_s == 0.0
    fe.on_window(timed)
    assert fe.tracker.time_offset_s == 0.003


def test_the_joint_marginal_prior_is_the_gaussian_it_was_built_from():
    """priors.marginal_prior over (pose, velocity, bias, extrinsics): a sum of block Hessian factors whose error at
    a perturbed point is 0.5 dx^T inv(cov) dx in the tangent (gtsam's retractions, bias order accelerometer then
    gyro)."""
    import gtsam
    from gtsam.symbol_shorthand import B, V, X

    from services.backend.window.extrinsics import extrinsic_key
    from services.backend.window.priors import marginal_prior

    rng = np.random.default_rng(0)
    vals = gtsam.Values()
    vals.insert(X(1), gtsam.Pose3(gtsam.Rot3.Ypr(0.1, 0.2, 0.3), np.array([1.0, 2.0, 3.0])))
    vals.insert(V(1), np.array([0.1, 0.2, 0.3]))
    vals.insert(B(1), gtsam.imuBias.ConstantBias(np.array([0.01, 0.02, 0.03]), np.array([1e-3, 2e-3, 3e-3])))
    keys = (extrinsic_key(0), extrinsic_key(1))
    for k, key in enumerate(keys):
        vals.insert(key, gtsam.Pose3(gtsam.Rot3.Ypr(0.3 * k, 0.1, 0.0), np.array([0.05 * k, 0.0, 0.01])))
    A = rng.normal(size=(27, 27))
    cov = A @ A.T * 1e-3 + np.eye(27) * 1e-4
    f = marginal_prior(vals, 1, cov, keys)
    assert f.error(vals) == pytest.approx(0.0, abs=1e-12)
    d = rng.normal(size=27) * 1e-3
    moved = gtsam.Values()
    moved.insert(X(1), vals.atPose3(X(1)).retract(d[0:6]))
    moved.insert(V(1), vals.atVector(V(1)) + d[6:9])
    b = vals.atConstantBias(B(1))
    moved.insert(B(1), gtsam.imuBias.ConstantBias(b.accelerometer() + d[9:12], b.gyroscope() + d[12:15]))
    for k, key in enumerate(keys):
        moved.insert(key, vals.atPose3(key).retract(d[15 + 6 * k:21 + 6 * k]))
    assert f.error(moved) == pytest.approx(0.5 * d @ np.linalg.solve(cov, d), rel=1e-9)
