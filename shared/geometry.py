"""SE(3) and quaternion helpers, the one set the project uses (numpy, vectorised over leading axes).

Conventions (BRIEF sec. 4): ``T_AB`` is a 4x4 float64 homogeneous matrix mapping points from frame B to
frame A (``p_A = T_AB @ p_B``); quaternions are Hamilton with the order in the name (``q_wxyz``).
Rotation vectors (axis * angle, rad) parametrise SO(3) through :func:`so3_exp` / :func:`so3_log`.
"""
from __future__ import annotations

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrix: ``skew(a) @ b == cross(a, b)``."""
    v = np.asarray(v, dtype=np.float64)
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2)


def so3_exp(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vector (..., 3) [rad] -> rotation matrix (..., 3, 3)."""
    r = np.asarray(rotvec, dtype=np.float64)
    theta = np.linalg.norm(r, axis=-1)[..., None, None]
    K = skew(r)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3) + a * K + b * (K @ K)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (..., 3, 3) -> rotation vector (..., 3) [rad], angle in [0, pi]."""
    return quat_wxyz_to_rotvec(R_to_quat_wxyz(R))


def quat_wxyz_to_R(q_wxyz: np.ndarray) -> np.ndarray:
    """Unit Hamilton quaternion (..., 4) in (w, x, y, z) order -> rotation matrix (..., 3, 3)."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


def R_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (..., 3, 3) -> unit quaternion (..., 4) (w, x, y, z) with w >= 0."""
    R = np.asarray(R, dtype=np.float64)
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    # four candidate solutions; take the numerically best per element (largest diagonal term)
    cands = np.stack([
        np.stack([1 + m00 + m11 + m22, R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1),
        np.stack([R[..., 2, 1] - R[..., 1, 2], 1 + m00 - m11 - m22, R[..., 0, 1] + R[..., 1, 0], R[..., 0, 2] + R[..., 2, 0]], -1),
        np.stack([R[..., 0, 2] - R[..., 2, 0], R[..., 0, 1] + R[..., 1, 0], 1 - m00 + m11 - m22, R[..., 1, 2] + R[..., 2, 1]], -1),
        np.stack([R[..., 1, 0] - R[..., 0, 1], R[..., 0, 2] + R[..., 2, 0], R[..., 1, 2] + R[..., 2, 1], 1 - m00 - m11 + m22], -1),
    ], -2)
    diag = np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    best = np.argmax(diag, axis=-1)
    q = np.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def quat_wxyz_to_rotvec(q_wxyz: np.ndarray) -> np.ndarray:
    q = np.asarray(q_wxyz, dtype=np.float64)
    q = np.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1)
    angle = 2.0 * np.arctan2(s, q[..., 0])
    scale = np.where(s < 1e-12, 2.0 / np.maximum(q[..., 0], 1e-12), angle / np.where(s < 1e-12, 1.0, s))
    return v * scale[..., None]


def quat_mul_wxyz(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a (x) b of (..., 4) quaternions in (w, x, y, z) order."""
    w1, x1, y1, z1 = np.moveaxis(np.asarray(a, float), -1, 0)
    w2, x2, y2, z2 = np.moveaxis(np.asarray(b, float), -1, 0)
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], axis=-1)


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Rotation (..., 3, 3) and translation (..., 3) -> homogeneous (..., 4, 4)."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    T = np.zeros(np.broadcast_shapes(R.shape[:-2], t.shape[:-1]) + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of homogeneous (..., 4, 4) rigid transforms: inv(T_AB) = T_BA."""
    T = np.asarray(T, dtype=np.float64)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    return make_T(Rt, -(Rt @ T[..., :3, 3:4])[..., 0])


def transform_points(T_AB: np.ndarray, p_B: np.ndarray) -> np.ndarray:
    """Apply one (4, 4) transform to points (N, 3) in B; returns points (N, 3) in A."""
    T_AB = np.asarray(T_AB, dtype=np.float64)
    return np.asarray(p_B, dtype=np.float64) @ T_AB[:3, :3].T + T_AB[:3, 3]


def pose_from_pq(p: np.ndarray, q_wxyz: np.ndarray) -> np.ndarray:
    """Position (..., 3) and Hamilton (w, x, y, z) quaternion (..., 4) -> T (..., 4, 4)."""
    return make_T(quat_wxyz_to_R(q_wxyz), p)


def pose_error(T_a: np.ndarray, T_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation [m] and rotation [rad] magnitudes of inv(T_a) @ T_b (vectorised)."""
    D = inv_T(T_a) @ np.asarray(T_b, float)
    return np.linalg.norm(D[..., :3, 3], axis=-1), np.linalg.norm(so3_log(D[..., :3, :3]), axis=-1)
