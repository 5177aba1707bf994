"""Continuous-time smooth trajectory of the body S in world W (C4 least-squares quintic B-splines).

Position: quintic least-squares B-spline per axis. Orientation: quintic least-squares B-spline of the
sign-continuous quaternion components, normalised on evaluation (smooth, C4 away from |u|=0).
Body rate omega_S = 2 vec(q^* (x) dq/dt). Times are int64 ns; internally seconds relative to t0.
"""
from __future__ import annotations

import numpy as np
from scipy.interpolate import make_lsq_spline

from shared.euroc import PoseSeries

_K = 5


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = np.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(b, -1, 0)
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], axis=-1)


def _knots(t: np.ndarray, spacing_s: float) -> tuple[float, np.ndarray]:
    """(spacing used, knot vector) of a least-squares spline over sample times ``t`` [s]. At least two samples per
    knot interval: a sparse ground truth (e.g. 20 Hz) gets a smoother fit instead of an underdetermined one."""
    spacing_s = max(float(spacing_s), 2.0 * float(np.median(np.diff(t))))
    n_int = max(1, int(np.ceil(t[-1] / spacing_s)))
    inner = np.linspace(t[0], t[-1], n_int + 1)[1:-1]
    return spacing_s, np.r_[[t[0]] * (_K + 1), inner, [t[-1]] * (_K + 1)]


def _quat_to_R(q: np.ndarray) -> np.ndarray:
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


class Trajectory:
    """Smooth trajectory fitted to a PoseSeries. ``knot_spacing_s`` sets the smoothing of the position and, unless
    ``rotation_knot_spacing_s`` is given, of the orientation too: a ground truth whose positions are noisier than
    its orientations (a laser tracker's) is best fitted with sparser position knots."""

    def __init__(self, poses: PoseSeries, knot_spacing_s: float = 0.1, rotation_knot_spacing_s: float | None = None):
        if len(poses) < 2 * (_K + 1):
            raise ValueError(f"trajectory needs at least {2 * (_K + 1)} poses, got {len(poses)}")
        self.t0_ns = int(poses.stamps_ns[0])
        self.t_end_ns = int(poses.stamps_ns[-1])
        t = (poses.stamps_ns - self.t0_ns) * 1e-9
        q = np.array(poses.q_WS_wxyz, dtype=np.float64)
        for i in range(1, len(q)):  # sign continuity
            if np.dot(q[i], q[i - 1]) < 0:
                q[i] = -q[i]
        self.knot_spacing_s, knots_p = _knots(t, knot_spacing_s)
        self.rotation_knot_spacing_s, knots_q = _knots(
            t, knot_spacing_s if rotation_knot_spacing_s is None else rotation_knot_spacing_s)
        self._p = make_lsq_spline(t, poses.p_WS, knots_p, k=_K)
        self._q = make_lsq_spline(t, q, knots_q, k=_K)

    def _s(self, stamps_ns) -> np.ndarray:
        s = (np.asarray(stamps_ns, dtype=np.int64) - self.t0_ns) * 1e-9
        if np.any(s < -1e-9) or np.any(s > (self.t_end_ns - self.t0_ns) * 1e-9 + 1e-9):
            raise ValueError("time outside the trajectory's span")
        return s

    def position(self, stamps_ns) -> np.ndarray:
        return self._p(self._s(stamps_ns))

    def velocity(self, stamps_ns) -> np.ndarray:
        return self._p(self._s(stamps_ns), 1)

    def acceleration(self, stamps_ns) -> np.ndarray:
        return self._p(self._s(stamps_ns), 2)

    def quaternion_wxyz(self, stamps_ns) -> np.ndarray:
        u = self._q(self._s(stamps_ns))
        return u / np.linalg.norm(u, axis=-1, keepdims=True)

    def rotation(self, stamps_ns) -> np.ndarray:
        return _quat_to_R(self.quaternion_wxyz(stamps_ns))

    def pose(self, stamps_ns) -> np.ndarray:
        """T_WS (..., 4, 4)."""
        R = self.rotation(stamps_ns)
        T = np.zeros(R.shape[:-2] + (4, 4))
        T[..., :3, :3] = R
        T[..., :3, 3] = self.position(stamps_ns)
        T[..., 3, 3] = 1.0
        return T

    def body_rate(self, stamps_ns) -> np.ndarray:
        """omega_S [rad/s]: angular velocity of S relative to W expressed in S."""
        s = self._s(stamps_ns)
        u, du = self._q(s), self._q(s, 1)
        n = np.linalg.norm(u, axis=-1, keepdims=True)
        q = u / n
        dq = (du - q * np.sum(q * du, axis=-1, keepdims=True)) / n
        conj = q * np.array([1.0, -1.0, -1.0, -1.0])
        return 2.0 * _qmul(conj, dq)[..., 1:]


def procedural(kind: str = "figure8", duration_s: float = 10.0, rate_hz: float = 200.0,
               t0_ns: int = 1_000_000_000) -> Trajectory:
    """Short synthetic trajectories for tests: 'figure8' (moving, rotating), 'static'."""
    n = int(duration_s * rate_hz) + 1
    stamps = t0_ns + np.round(np.arange(n) / rate_hz * 1e9).astype(np.int64)
    t = np.arange(n) / rate_hz
    if kind == "static":
        p = np.tile([0.5, -0.2, 1.0], (n, 1))
        yaw = np.full(n, 0.3)
        roll = np.zeros(n)
    elif kind == "figure8":
        w = 2 * np.pi / duration_s
        p = np.column_stack([1.5 * np.sin(w * t), 0.8 * np.sin(2 * w * t), 1.0 + 0.2 * np.sin(3 * w * t)])
        yaw = 0.8 * np.sin(w * t)
        roll = 0.2 * np.sin(2 * w * t)
    else:
        raise ValueError(f"unknown procedural trajectory {kind!r}")
    qz = np.column_stack([np.cos(yaw / 2), 0 * yaw, 0 * yaw, np.sin(yaw / 2)])
    qx = np.column_stack([np.cos(roll / 2), np.sin(roll / 2), 0 * roll, 0 * roll])
    return Trajectory(PoseSeries(stamps, p, _qmul(qz, qx)), knot_spacing_s=0.05)
