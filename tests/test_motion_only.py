"""The motion-only solve (shared/vio/motion_only.py): its pose Jacobians against finite differences of gtsam's
retraction, and its solution against gtsam's Levenberg-Marquardt on the same cost written as a graph (landmarks and
keyframe as variables pinned by tight priors), with an IMU factor, outliers under the Cauchy loss and a point behind
a camera."""

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import B, L, V, X

from shared.vio.cameras import VioCamera
from services.backend.config import BackendConfig
from shared.vio.imu_factors import imu_factor, make_bias, make_params, predict
from shared.vio.motion_only import _residuals, optimise_latest
from shared.vio.vision_factors import ProjectionModel
from shared.geometry import so3_exp

pytestmark = pytest.mark.unit


def _rig():
    T0, T1 = np.eye(4), np.eye(4)
    T0[:3, :3] = so3_exp(np.array([0.05, -0.1, 0.02]))
    T1[:3, :3], T1[:3, 3] = so3_exp(np.array([0.02, 0.05, -0.03])), [0.11, 0.0, 0.01]
    return [VioCamera(T_SC=T, undistort=lambda uv: uv, focal_px=460.0) for T in
            (T0, T1)]


def _problem(seed: int, n_pts: int = 60, outliers: int = 6):
    """A keyframe at rest, 0.2 s of IMU to the frame, observations of fixed points with 1 px noise and outliers."""
    rng = np.random.default_rng(seed)
    cfg = BackendConfig()
    model = ProjectionModel(_rig(), cfg.sigma_px, cfg.cauchy_k)
    bias = make_bias(np.array([0.002, -0.001, 0.003]), np.array([0.05, -0.03, 0.02]))
    pim = gtsam.PreintegratedCombinedMeasurements(make_params(cfg), bias)
    omega, acc = np.array([0.1, -0.2, 0.3]), np.array([0.3, 0.1, 9.81])
    for _ in range(40):
        pim.integrateMeasurement(acc + rng.normal(0, 0.02, 3), omega + rng.normal(0, 0.002, 3), 0.005)
    T_k = np.eye(4)
    T_k[:3, 3] = [1.0, 2.0, 0.5]
    v_k = np.array([0.4, -0.1, 0.0])
    T_true, v_true = predict(pim, T_k, v_k, bias)
    cams = rng.integers(0, 2, n_pts)
    p_C = np.c_[rng.uniform(-1, 1, (n_pts, 2)) * 2.0, rng.uniform(2.0, 6.0, n_pts)]
    T_WC = T_true @ model._T_SC[cams]
    p_W = np.einsum("mij,mj->mi", T_WC[:, :3, :3], p_C) + T_WC[:, :3, 3]
    xy = p_C[:, :2] / p_C[:, 2:] + rng.normal(0, 1.0 / 460.0, (n_pts, 2))
    xy[:outliers] += rng.uniform(-0.05, 0.05, (outliers, 2))  # 5-20 px off: the Cauchy loss's business
    p_W[outliers] = T_true[:3, 3] - 2.0 * (T_WC[outliers, :3, 2])  # behind its camera
    values = gtsam.Values()
    T_guess = gtsam.Pose3(T_true).retract(np.r_[rng.normal(0, 0.01, 3), rng.normal(0, 0.03, 3)])
    for key, val in ((X(0), gtsam.Pose3(T_k)), (V(0), v_k), (B(0), bias), (X(1), T_guess), (V(1), v_true + 0.05),
                     (B(1), bias)):
        values.insert(key, val)
    factor = imu_factor(pim, (X(0), V(0), B(0)), (X(1), V(1), B(1)))
    return model, values, factor, p_W, xy, cams, T_true


def test_pose_jacobians_match_finite_differences():
    model, values, _, p_W, xy, cams, _ = _problem(1)
    pts = model.fixed_points(p_W, xy, cams)
    T = values.atPose3(X(1))
    e, front, J = _residuals(T.matrix(), pts, True)
    assert (~front).sum() == 1 and np.all(J[~front] == 0)
    for i in range(6):
        d = np.zeros(6)
        d[i] = 1e-6
        num = (_residuals(T.retract(d).matrix(), pts, False)[0] - _residuals(T.retract(-d).matrix(), pts, False)[0]) / 2e-6
        assert np.allclose(num[front], J[front, :, i], rtol=1e-5, atol=1e-4), i


@pytest.mark.parametrize("seed", [2, 3, 4])
def test_solution_equals_gtsam_with_pinned_landmarks(seed):
    model, values, factor, p_W, xy, cams, T_true = _problem(seed)
    out = optimise_latest(values, 1, [factor], model.fixed_points(p_W, xy, cams), iterations=20)
    # the same cost as a gtsam graph: landmarks and keyframe pinned (sigma 1e-6), Levenberg-Marquardt to convergence
    g, v = gtsam.NonlinearFactorGraph(), gtsam.Values(values)
    pin = 1e-6
    g.add(gtsam.PriorFactorPose3(X(0), values.atPose3(X(0)), gtsam.noiseModel.Isotropic.Sigma(6, pin)))
    g.add(gtsam.PriorFactorVector(V(0), values.atVector(V(0)), gtsam.noiseModel.Isotropic.Sigma(3, pin)))
    g.add(gtsam.PriorFactorConstantBias(B(0), values.atConstantBias(B(0)), gtsam.noiseModel.Isotropic.Sigma(6, pin)))
    g.add(factor)
    for i, (p, c, q) in enumerate(zip(p_W, cams, xy)):
        if i == 6:  # gtsam's cheirality handling differs (a constant error): the point behind is left out
            continue
        g.add(gtsam.PriorFactorPoint3(L(i), p, gtsam.noiseModel.Isotropic.Sigma(3, pin)))
        v.insert(L(i), p)
        g.add(model.factor(q, int(c), X(1), L(i)))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-12)
    ref = gtsam.LevenbergMarquardtOptimizer(g, v, params).optimize()
    T_ours, T_ref = out.atPose3(X(1)).matrix(), ref.atPose3(X(1)).matrix()
    assert np.linalg.norm(T_ours[:3, 3] - T_ref[:3, 3]) < 1e-6
    assert np.linalg.norm(T_ours[:3, :3] - T_ref[:3, :3]) < 1e-6
    assert np.linalg.norm(np.asarray(out.atVector(V(1))) - np.asarray(ref.atVector(V(1)))) < 1e-5
    assert np.allclose(out.atConstantBias(B(1)).vector(), ref.atConstantBias(B(1)).vector(), atol=1e-6)
    # and it is the truth to within the noise (the outliers did not pull it away)
    assert np.linalg.norm(T_ours[:3, 3] - T_true[:3, 3]) < 0.01


def test_an_unconstrained_state_is_an_error():
    model, values, _, p_W, xy, cams, _ = _problem(5)
    with pytest.raises(RuntimeError):
        optimise_latest(values, 1, [], model.fixed_points(p_W[:1], xy[:1], cams[:1]), iterations=3)
