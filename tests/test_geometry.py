import numpy as np
from scipy.spatial.transform import Rotation

from shared import geometry as g


def test_quaternion_matches_scipy_and_round_trips():
    rng = np.random.default_rng(0)
    R = Rotation.random(200, random_state=1)
    xyzw = R.as_quat()
    q_wxyz = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
    np.testing.assert_allclose(g.quat_wxyz_to_R(q_wxyz), R.as_matrix(), atol=1e-12)
    back = g.R_to_quat_wxyz(R.as_matrix())
    assert np.all(back[:, 0] >= 0)
    np.testing.assert_allclose(np.abs(np.sum(back * q_wxyz, axis=1)), 1.0, atol=1e-12)
    # Hamilton product composes like rotation matrices
    a, b = q_wxyz[:100], q_wxyz[100:]
    np.testing.assert_allclose(g.quat_wxyz_to_R(g.quat_mul_wxyz(a, b)),
                               g.quat_wxyz_to_R(a) @ g.quat_wxyz_to_R(b), atol=1e-12)
    v = rng.normal(size=(50, 3))
    np.testing.assert_allclose(g.skew(v[:1])[0] @ v[1], np.cross(v[0], v[1]), atol=1e-12)


def test_exp_log_and_transforms():
    rng = np.random.default_rng(2)
    rv = rng.normal(size=(100, 3))
    rv *= (rng.uniform(0, np.pi - 1e-3, 100) / np.linalg.norm(rv, axis=1))[:, None]
    rv[0] = [1e-10, 0, 0]
    R = g.so3_exp(rv)
    np.testing.assert_allclose(R, Rotation.from_rotvec(rv).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(g.so3_log(R), rv, atol=1e-9)
    T = g.make_T(R, rng.normal(size=(100, 3)))
    np.testing.assert_allclose(g.inv_T(T) @ T, np.broadcast_to(np.eye(4), T.shape), atol=1e-12)
    p = rng.normal(size=(7, 3))
    np.testing.assert_allclose(g.transform_points(T[3], p), (T[3] @ np.c_[p, np.ones(7)].T).T[:, :3], atol=1e-12)
    dt, dr = g.pose_error(T, T)
    assert np.all(dt < 1e-12) and np.all(dr < 1e-6)
