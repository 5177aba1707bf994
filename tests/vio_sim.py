"""Tiny visual-inertial test-data generator for back-end tests (not the production simulator).

A smooth procedural trajectory (positions and Z-Y-X Euler angles as sums of sines, so velocity,
acceleration and body rates are analytic), IMU readings (specific force and rate in S, optional white noise
and bias random walk), random landmarks on a cylinder wall around the path, and their projections into
an N-camera rig (pinhole + optional radial-tangential distortion via OpenCV) with pixel noise.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

G_W = np.array([0.0, 0.0, -9.81])


def _sines(t, amp, freq, phase, deriv):
    """sum_k amp_k sin(freq_k t + phase_k), differentiated ``deriv`` times; t (N,), params (3,K) -> (N,3)."""
    t = np.asarray(t, float)[:, None, None]
    arg = freq[None] * t + phase[None]
    vals = [np.sin, np.cos, lambda x: -np.sin(x)][deriv](arg) * amp[None] * freq[None] ** deriv
    return vals.sum(axis=2)


def _rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


@dataclass
class Trajectory:
    """Body S in W: p_W(t) and Euler angles (roll, pitch, yaw)(t), each a sum of sines plus a linear term."""

    p_amp: np.ndarray = field(default_factory=lambda: np.array([[1.5, 0.2], [1.5, 0.1], [0.3, 0.0]]))
    p_freq: np.ndarray = field(default_factory=lambda: np.array([[0.5, 1.3], [0.5, 1.1], [0.9, 1.0]]))
    p_phase: np.ndarray = field(default_factory=lambda: np.array([[np.pi / 2, 0.0], [0.0, 0.5], [0.0, 0.0]]))
    e_amp: np.ndarray = field(default_factory=lambda: np.array([[0.15, 0.0], [0.1, 0.0], [0.6, 0.0]]))
    e_freq: np.ndarray = field(default_factory=lambda: np.array([[0.8, 1.0], [0.6, 1.0], [0.5, 1.0]]))
    e_phase: np.ndarray = field(default_factory=lambda: np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 0.0]]))
    yaw_rate: float = 0.3
    scale: float = 1.0  # multiplies all motion (0: static)

    def position(self, t):
        return self.scale * _sines(t, self.p_amp, self.p_freq, self.p_phase, 0)

    def velocity(self, t):
        return self.scale * _sines(t, self.p_amp, self.p_freq, self.p_phase, 1)

    def acceleration(self, t):
        return self.scale * _sines(t, self.p_amp, self.p_freq, self.p_phase, 2)

    def euler(self, t, deriv=0):
        e = self.scale * _sines(t, self.e_amp, self.e_freq, self.e_phase, deriv)
        e[:, 2] += self.scale * self.yaw_rate * (np.asarray(t, float) if deriv == 0 else (deriv == 1))
        return e

    def rotation(self, t):
        return np.array([_rz(y) @ _ry(p) @ _rx(r) for r, p, y in self.euler(t)])

    def T_WS(self, t):
        T = np.tile(np.eye(4), (len(np.atleast_1d(t)), 1, 1))
        T[:, :3, :3] = self.rotation(t)
        T[:, :3, 3] = self.position(t)
        return T

    def omega_S(self, t):
        e, de = self.euler(t), self.euler(t, 1)
        out = []
        for (r, p, _), (dr, dp, dy) in zip(e, de):
            Rx, Ry = _rx(r), _ry(p)
            out.append(Rx.T @ Ry.T @ [0, 0, dy] + Rx.T @ [0, dp, 0] + [dr, 0, 0])
        return np.array(out)

    def acc_S(self, t):
        R = self.rotation(t)
        return np.einsum("nji,nj->ni", R, self.acceleration(t) - G_W)


class Pausing:
    """``base`` played until ``t_stop``, then brought to a stand smoothly (time warp s(t) = t_stop + tau (1 -
    exp(-(t - t_stop) / tau)): the body slows down exponentially and stands still after a few tau)."""

    def __init__(self, base: Trajectory, t_stop: float, tau: float = 0.3):
        self.base, self.t_stop, self.tau = base, t_stop, tau

    def _warp(self, t):
        t = np.asarray(t, float)
        d = np.maximum(t - self.t_stop, 0.0)
        e = np.exp(-d / self.tau)
        moving = t <= self.t_stop
        s = np.where(moving, t, self.t_stop + self.tau * (1 - e))
        ds = np.where(moving, 1.0, e)
        dds = np.where(moving, 0.0, -e / self.tau)
        return s, ds, dds

    def position(self, t):
        return self.base.position(self._warp(t)[0])

    def velocity(self, t):
        s, ds, _ = self._warp(t)
        return self.base.velocity(s) * ds[:, None]

    def acceleration(self, t):
        s, ds, dds = self._warp(t)
        return self.base.acceleration(s) * (ds ** 2)[:, None] + self.base.velocity(s) * dds[:, None]

    def euler(self, t, deriv=0):
        s, ds, _ = self._warp(t)
        return self.base.euler(s) if deriv == 0 else self.base.euler(s, 1) * ds[:, None]

    rotation, T_WS, omega_S, acc_S = Trajectory.rotation, Trajectory.T_WS, Trajectory.omega_S, Trajectory.acc_S


def imu(traj: Trajectory, t0: float, t1: float, rate_hz: float = 200.0, rng=None, gyro_nd=0.0, acc_nd=0.0,
        gyro_rw=0.0, acc_rw=0.0, gyro_bias=(0, 0, 0), acc_bias=(0, 0, 0)):
    """IMU samples over [t0, t1] s: (stamps_ns int64, omega_S, acc_S); noise densities are continuous-time."""
    n = int(round((t1 - t0) * rate_hz)) + 1
    t = t0 + np.arange(n) / rate_hz
    omega, acc = traj.omega_S(t), traj.acc_S(t)
    if rng is not None:
        dt = 1.0 / rate_hz
        bg = np.asarray(gyro_bias, float) + np.cumsum(rng.normal(0, gyro_rw * np.sqrt(dt), (n, 3)), axis=0)
        ba = np.asarray(acc_bias, float) + np.cumsum(rng.normal(0, acc_rw * np.sqrt(dt), (n, 3)), axis=0)
        omega = omega + bg + rng.normal(0, gyro_nd / np.sqrt(dt), (n, 3))
        acc = acc + ba + rng.normal(0, acc_nd / np.sqrt(dt), (n, 3))
    return np.round(t * 1e9).astype(np.int64), omega, acc


def landmarks_cylinder(n: int, radius=(4.0, 6.0), z=(-1.5, 2.5), seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = rng.uniform(0, 2 * np.pi, n)
    r = rng.uniform(*radius, n)
    return np.stack([r * np.cos(a), r * np.sin(a), rng.uniform(*z, n)], axis=1)


@dataclass
class SimCamera:
    T_SC: np.ndarray
    K: np.ndarray
    dist: np.ndarray  # OpenCV radtan (k1, k2, p1, p2)
    size: tuple = (640, 480)

    def project(self, p_C: np.ndarray) -> np.ndarray:
        uv, _ = cv2.projectPoints(p_C.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.K, self.dist)
        return uv.reshape(-1, 2)

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        """Normalised image coordinates (x/z, y/z) of distorted pixels."""
        k1, k2, p1, p2 = self.dist
        d = (np.asarray(uv, float) - self.K[:2, 2]) / np.diag(self.K)[:2]
        xy = d.copy()
        for _ in range(30):  # fixed-point inversion of the radial-tangential model
            x, y = xy[:, 0], xy[:, 1]
            r2 = x * x + y * y
            radial = 1 + k1 * r2 + k2 * r2 * r2
            dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
            xy = np.stack([(d[:, 0] - dx) / radial, (d[:, 1] - dy) / radial], axis=1)
        return xy


def rig(n_cams: int = 3, dist=(0.0, 0.0, 0.0, 0.0), f=400.0) -> list[SimCamera]:
    """n cameras looking outward, spread in yaw around body x (x forward, z up); optical axes horizontal."""
    K = np.array([[f, 0, 320.0], [0, f, 240.0], [0, 0, 1]])
    R_S_C0 = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)  # camera z along body x, y down
    cams = []
    for i in range(n_cams):
        T = np.eye(4)
        T[:3, :3] = _rz(2 * np.pi * i / n_cams) @ R_S_C0
        T[:3, 3] = [0.05 * np.cos(2 * np.pi * i / n_cams), 0.05 * np.sin(2 * np.pi * i / n_cams), 0.02]
        cams.append(SimCamera(T, K, np.asarray(dist, float)))
    return cams


def observe(T_WS: np.ndarray, points_W: np.ndarray, cams: list[SimCamera], sigma_px=0.0, rng=None,
            max_per_cam=40):
    """(landmark_ids int64, camera_index int16, uv float32 (M,2)) of the points visible in each camera.

    The lowest visible ids are kept (stable tracks from frame to frame, like a tracker would keep)."""
    ids, cidx, uvs = [], [], []
    for c, cam in enumerate(cams):
        T_CW = np.linalg.inv(T_WS @ cam.T_SC)
        p_C = points_W @ T_CW[:3, :3].T + T_CW[:3, 3]
        front = np.flatnonzero(p_C[:, 2] > 0.3)
        if len(front) == 0:
            continue
        uv = cam.project(p_C[front])
        ok = (uv[:, 0] >= 0) & (uv[:, 0] < cam.size[0]) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.size[1])
        sel = front[ok][:max_per_cam]
        uv = uv[ok][:max_per_cam]
        if rng is not None and sigma_px > 0:
            uv = uv + rng.normal(0, sigma_px, uv.shape)
        ids.append(sel)
        cidx.append(np.full(len(sel), c))
        uvs.append(uv)
    if not ids:
        return np.zeros(0, np.int64), np.zeros(0, np.int16), np.zeros((0, 2), np.float32)
    return (np.concatenate(ids).astype(np.int64), np.concatenate(cidx).astype(np.int16),
            np.concatenate(uvs).astype(np.float32))
