"""ATE: recovers known alignments exactly and agrees with evo on random trajectories."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from shared.metrics.ate import align_posyaw, associate, compute_ate, umeyama


def _trajectory(n=400, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 50_000_000 + 1_000_000_000
    s = np.linspace(0, 4 * np.pi, n)
    p = np.stack([2 * np.cos(s), 1.5 * np.sin(2 * s), 1 + 0.3 * np.sin(3 * s)], 1) + rng.normal(0, 0.01, (n, 3))
    return t.astype(np.int64), p


def test_umeyama_recovers_similarity_exactly():
    _, p = _trajectory()
    R = Rotation.from_euler("zyx", [0.7, -0.2, 0.4]).as_matrix()
    t = np.array([1.0, -2.0, 0.5])
    q = 1.7 * p @ R.T + t
    al = umeyama(p, q, with_scale=True)
    np.testing.assert_allclose(al.R, R, atol=1e-10)
    np.testing.assert_allclose(al.t, t, atol=1e-10)
    assert al.scale == pytest.approx(1.7, abs=1e-10)
    assert umeyama(p, q, with_scale=False).scale == 1.0


def test_posyaw_recovers_yaw_and_translation_and_ignores_tilt():
    _, p = _trajectory()
    R = Rotation.from_euler("z", 1.1).as_matrix()
    al = align_posyaw(p, p @ R.T + [3, 4, 5])
    np.testing.assert_allclose(al.R, R, atol=1e-10)
    np.testing.assert_allclose(al.t, [3, 4, 5], atol=1e-10)


def test_ate_is_zero_for_a_transformed_copy_and_equals_injected_error():
    t, p = _trajectory()
    R = Rotation.from_euler("xyz", [0.3, 0.1, -0.8]).as_matrix()
    est = (p - [1, 2, 3]) @ R
    assert compute_ate(t, p, t, est).rmse_m < 1e-9
    # a constant offset along a known direction on half of the poses cannot be aligned away fully
    rng = np.random.default_rng(1)
    noise = rng.normal(0, 0.05, p.shape)
    res = compute_ate(t, p, t, p + noise, mode="none")
    assert res.rmse_m == pytest.approx(np.sqrt((noise ** 2).sum(1).mean()), rel=1e-12)


def test_association_with_tolerance():
    a = np.array([0, 10, 20, 35], np.int64)
    b = np.array([21, 1, 9, 100], np.int64)
    ia, ib = associate(a, b, max_diff_ns=2)
    assert ia.tolist() == [0, 1, 2] and b[ib].tolist() == [1, 9, 21]


def test_errors_are_clear():
    t, p = _trajectory(5)
    with pytest.raises(ValueError, match="unknown alignment mode"):
        compute_ate(t, p, t, p, mode="bogus")
    with pytest.raises(ValueError, match="have ground truth within"):
        compute_ate(t, p, t + 10**9, p)


@pytest.mark.parametrize("with_scale", [False, True])
def test_agrees_with_evo(with_scale):
    from evo.core import metrics, sync
    from evo.core.trajectory import PoseTrajectory3D

    t, p = _trajectory(300, seed=3)
    rng = np.random.default_rng(4)
    R = Rotation.from_rotvec([0.2, -0.5, 1.0]).as_matrix()
    est = 0.9 * (p + np.cumsum(rng.normal(0, 0.003, p.shape), 0)) @ R.T + [0.5, 0.1, -0.3]
    q_wxyz = np.tile([1.0, 0, 0, 0], (len(t), 1))
    traj_gt = PoseTrajectory3D(positions_xyz=p, orientations_quat_wxyz=q_wxyz, timestamps=t / 1e9)
    traj_est = PoseTrajectory3D(positions_xyz=est, orientations_quat_wxyz=q_wxyz, timestamps=t / 1e9)
    traj_gt, traj_est = sync.associate_trajectories(traj_gt, traj_est)
    traj_est.align(traj_gt, correct_scale=with_scale)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((traj_gt, traj_est))
    ours = compute_ate(t, p, t, est, mode="sim3" if with_scale else "se3")
    assert ours.rmse_m == pytest.approx(ape.get_statistic(metrics.StatisticsType.rmse), rel=1e-9)
