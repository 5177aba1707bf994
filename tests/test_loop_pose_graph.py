"""Pose graph (relative-pose factors from marginal covariances, loop factors) and covisibility, without
transport: drift reduction against ground truth, the relative-pose covariance against sampling."""

import gtsam
import numpy as np
import pytest

from services.backend.loop.covisibility import Covisibility
from services.backend.loop.pose_graph import LoopConstraint, PoseGraph, relative_covariance
from shared.geometry import inv_T, so3_exp
from services.app.synth.trajectory import procedural


def _exp(xi):
    return gtsam.Pose3.Expmap(np.asarray(xi, float)).matrix()


def _log(T):
    return gtsam.Pose3.Logmap(gtsam.Pose3(T))


def test_relative_covariance_matches_sampling():
    rng = np.random.default_rng(0)
    T_WA = np.eye(4)
    T_WA[:3, :3], T_WA[:3, 3] = so3_exp([0.3, -0.2, 1.0]), [1.0, 2.0, 0.5]
    T_WB = T_WA @ _exp([0.1, 0.05, -0.2, 0.8, -0.3, 0.1])
    A = rng.normal(size=(12, 12)) * 0.01
    joint = A @ A.T + np.eye(12) * 1e-5  # correlated poses, like two keyframes of one window
    C = relative_covariance(T_WA, T_WB, joint)
    T_AB = inv_T(T_WA) @ T_WB
    xs = rng.multivariate_normal(np.zeros(12), joint, size=20000)
    errs = np.array([_log(inv_T(T_AB) @ inv_T(T_WA @ _exp(x[:6])) @ (T_WB @ _exp(x[6:]))) for x in xs])
    emp = np.cov(errs.T)
    assert np.allclose(C, emp, atol=0.05 * np.abs(emp).max()), np.abs(C - emp).max()


def _drifting_odometry(n=60, seed=1):
    """Keyframe poses of a closed path (figure 8, twice) and odometry with a steady yaw + forward drift."""
    traj = procedural("figure8", duration_s=20.0)
    stamps = np.linspace(traj.t0_ns, traj.t_end_ns, n).astype(np.int64)
    gt = np.array([traj.pose(s) for s in stamps])
    rng = np.random.default_rng(seed)
    sig = np.array([2e-3] * 3 + [5e-3] * 3)
    drift = np.array([0, 0, 4e-3, 8e-3, 0, 0])  # per step: 0.23 deg yaw, 8 mm along x of the body
    odom = [gt[0]]
    rels = []
    for a, b in zip(gt[:-1], gt[1:]):
        rel = inv_T(a) @ b @ _exp(drift + rng.normal(0, sig))
        rels.append(rel)
        odom.append(odom[-1] @ rel)
    return stamps, gt, np.array(odom), np.diag(sig ** 2 + drift ** 2)


def _rmse(T, gt):
    return float(np.sqrt(np.mean(np.sum((T[:, :3, 3] - gt[:, :3, 3]) ** 2, axis=1))))


def test_loop_factor_reduces_drift():
    stamps, gt, odom, cov = _drifting_odometry()
    pg = PoseGraph()
    for k, T in enumerate(odom):
        pg.add_node(k, T, None if k == 0 else cov)
    before = _rmse(np.array([pg.estimate[k] for k in range(len(odom))]), gt)
    assert before > 0.2  # the drift is substantial
    n = len(odom)
    # the path passes its start again half-way and at the end: two loops measured from ground truth (+ noise)
    rng = np.random.default_rng(2)
    loop_cov = np.diag([1e-6] * 3 + [1e-4] * 3)
    for old, new in ((0, n // 2 - 1), (0, n - 1), (5, n // 2 + 4)):
        T_rel = inv_T(gt[old]) @ gt[new] @ _exp(rng.normal(0, np.sqrt(np.diag(loop_cov))))
        pg.add_loop(LoopConstraint(old, new, T_rel, loop_cov))
    est = pg.optimise()
    after = _rmse(np.array([est[k] for k in range(n)]), gt)
    assert after < 0.25 * before, (before, after)
    # the correction maps the newest odometry pose onto its corrected pose
    assert np.allclose(pg.correction() @ odom[-1], est[n - 1], atol=1e-9)
    # a wrong loop (robust factor) does not wreck the graph
    pg.add_loop(LoopConstraint(0, n // 4, _exp([0, 0, 1.0, 2.0, -1.0, 0]), loop_cov))
    est2 = pg.optimise()
    assert _rmse(np.array([est2[k] for k in range(n)]), gt) < 0.5 * before


def test_pose_graph_rejects_missing_covariance_and_unknown_loop_nodes():
    pg = PoseGraph()
    pg.add_node(0, np.eye(4))
    with pytest.raises(ValueError):
        pg.add_node(1, np.eye(4), None)
    with pytest.raises(KeyError):
        pg.add_loop(LoopConstraint(0, 7, np.eye(4), np.eye(6)))


def test_covisibility_queries():
    cv = Covisibility()
    cv.add_keyframe(0, [1, 2, 3, 4])
    cv.add_keyframe(1, [3, 4, 5, 6])
    cv.add_keyframe(2, [4, 5, 6, 7, 7])
    cv.add_keyframe(3, [100])
    assert list(cv.covisible(1).items()) == [(2, 3), (0, 2)]  # most shared first
    assert cv.covisible(2, min_shared=3) == {1: 3}
    assert cv.shared(0, 2) == 1 and cv.shared(0, 3) == 0
    assert cv.keyframes(4) == [0, 1, 2]
    assert cv.oldest_covisible(2, 1) == 0 and cv.oldest_covisible(2, 3) == 1 and cv.oldest_covisible(3, 1) is None
    assert cv.covisible_with_landmarks([5, 6, 7]) == {2: 3, 1: 2}
    cv.add_keyframe(0, [100])  # replacing a keyframe's landmarks updates the inverse index
    assert cv.keyframes(1) == [] and cv.oldest_covisible(3, 1) == 0


def test_corrected_state_moves_pose_velocity_and_covariance_consistently():
    from shared.vio.states import corrected_state
    from shared.messages import EstimatorState, Header

    rng = np.random.default_rng(4)
    A = rng.normal(size=(15, 15))
    T_WS = _exp([0.1, 0.2, 0.3, 1.0, 2.0, 3.0])
    msg = EstimatorState(header=Header(stamp_ns=1), T_WS=T_WS, v_W=np.array([1.0, 0.0, 0.0]), gyro_bias=np.zeros(3),
                         acc_bias=np.zeros(3), covariance=A @ A.T, status="tracking")
    T = _exp([0.0, 0.0, 0.5, 0.2, -0.1, 0.0])
    out = corrected_state(msg, T)
    assert np.allclose(out.T_WS, T @ T_WS) and np.allclose(out.v_W, T[:3, :3] @ msg.v_W)
    # sampled p_W perturbations, moved by T, have the transformed position covariance
    P = msg.covariance[3:6, 3:6]
    xs = rng.multivariate_normal(np.zeros(3), P, 20000) @ T[:3, :3].T
    assert np.allclose(np.cov(xs.T), out.covariance[3:6, 3:6], atol=0.05 * np.abs(P).max())
    assert np.allclose(out.covariance[0:3, 0:3], msg.covariance[0:3, 0:3])  # body-frame rotation block unchanged


def _tilt_between(Ta, Tb):
    """Angle between the up directions two poses give the body frame [deg] (a yaw leaves it 0)."""
    ua, ub = Ta[:3, :3].T @ [0, 0, 1.0], Tb[:3, :3].T @ [0, 0, 1.0]
    return float(np.degrees(np.arccos(np.clip(ua @ ub, -1.0, 1.0))))


@pytest.mark.parametrize("attitude_sigma_deg", [0.0, 0.2])
def test_attitude_factors_keep_the_windows_tilt_against_a_tilting_loop(attitude_sigma_deg):
    # odometry with yaw and position drift only (roll and pitch are observable in VIO); the three loops of
    # test_loop_factor_reduces_drift, right in yaw and position but tilted by 1 deg (as a biased map-to-map term
    # can be): without the attitude factors the graph tilts the keyframes, with them it keeps their tilt and
    # still removes the drift
    stamps, gt, odom, cov = _drifting_odometry()
    n = len(odom)
    pg = PoseGraph(attitude_sigma_rad=np.deg2rad(attitude_sigma_deg))
    for k, T in enumerate(odom):
        pg.add_node(k, T, None if k == 0 else cov)
    before = _rmse(np.array([pg.estimate[k] for k in range(n)]), gt)
    tilt = _exp([np.deg2rad(1.0), 0, 0, 0, 0, 0])
    loop_cov = np.diag([np.deg2rad(0.5) ** 2] * 3 + [1e-4] * 3)
    for old, new in ((0, n // 2 - 1), (0, n - 1), (5, n // 2 + 4)):
        pg.add_loop(LoopConstraint(old, new, inv_T(gt[old]) @ gt[new] @ tilt, loop_cov))
    est = pg.optimise()
    worst = max(_tilt_between(est[k], odom[k]) for k in range(n))
    after = _rmse(np.array([est[k] for k in range(n)]), gt)
    print(f"attitude sigma {attitude_sigma_deg} deg: largest tilt change {worst:.3f} deg, RMSE {before:.3f} -> {after:.3f} m")
    if attitude_sigma_deg > 0:
        assert worst < 0.1, worst
        assert after < 0.5 * before, (before, after)
    else:
        assert worst > 0.3, worst  # the 6-DoF graph follows the tilted loops
