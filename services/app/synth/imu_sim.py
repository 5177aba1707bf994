"""IMU from a trajectory (simulated) or from a recorded EuRoC imu0 CSV (real), and a time-alignment check.

Model: omega_S = omega_true + b_g + n_g, acc_S = R_WS^T (a_W - g_W) + b_a + n_a, g_W = (0, 0, -9.81);
discrete white noise sigma_d = density * sqrt(rate); biases are random walks with per-step
sigma = random_walk / sqrt(rate). ``noise`` may be any object with the attributes of calib.ImuCalib.
"""
from __future__ import annotations

import lzma
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.app.synth.trajectory import Trajectory

G_W = np.array([0.0, 0.0, -9.81])


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time noise densities (defaults: EuRoC imu0, ADIS16448)."""
    gyro_noise_density: float = 1.6968e-04  # rad/s/sqrt(Hz)
    gyro_random_walk: float = 1.9393e-05  # rad/s^2/sqrt(Hz)
    accel_noise_density: float = 2.0e-3  # m/s^2/sqrt(Hz)
    accel_random_walk: float = 3.0e-3  # m/s^3/sqrt(Hz)


@dataclass(frozen=True)
class ImuData:
    stamps_ns: np.ndarray  # int64 (N,)
    omega_S: np.ndarray  # (N, 3) rad/s
    acc_S: np.ndarray  # (N, 3) m/s^2
    gyro_bias: np.ndarray | None = None  # (N, 3) true bias (simulated only)
    accel_bias: np.ndarray | None = None


def simulate_imu(traj: Trajectory, stamps_ns: np.ndarray, noise=None, seed: int = 0,
                 gyro_bias0=(0.0, 0.0, 0.0), accel_bias0=(0.0, 0.0, 0.0)) -> ImuData:
    """Simulate imu0 at ``stamps_ns`` (uniform rate assumed for the noise); ``noise=None`` -> noise-free."""
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    R = traj.rotation(stamps_ns)
    omega = traj.body_rate(stamps_ns)
    acc = np.einsum("nji,nj->ni", R, traj.acceleration(stamps_ns) - G_W)
    n = len(stamps_ns)
    bg = np.tile(np.asarray(gyro_bias0, float), (n, 1))
    ba = np.tile(np.asarray(accel_bias0, float), (n, 1))
    if noise is not None:
        rate = 1e9 / np.median(np.diff(stamps_ns))
        rng = np.random.default_rng(seed)
        bg = bg + np.cumsum(rng.normal(size=(n, 3)) * noise.gyro_random_walk / np.sqrt(rate), axis=0)
        ba = ba + np.cumsum(rng.normal(size=(n, 3)) * noise.accel_random_walk / np.sqrt(rate), axis=0)
        omega = omega + rng.normal(size=(n, 3)) * noise.gyro_noise_density * np.sqrt(rate)
        acc = acc + rng.normal(size=(n, 3)) * noise.accel_noise_density * np.sqrt(rate)
    return ImuData(stamps_ns, omega + bg, acc + ba, bg, ba)


def read_imu_csv(path: str | Path) -> ImuData:
    """Read EuRoC imu0 data.csv (``t_ns, w xyz, a xyz``; .xz ok). Rows whose time does not increase -> ValueError."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: IMU file not found")
    opener = lzma.open if path.suffix == ".xz" else open
    stamps, vals = [], []
    with opener(path, "rt") as f:
        for lineno, line in enumerate(f, 1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            parts = s.split(",")
            if len(parts) != 7:
                raise ValueError(f"{path}:{lineno}: expected 7 columns, got {len(parts)}")
            stamps.append(int(parts[0]))
            vals.append([float(x) for x in parts[1:]])
    t = np.asarray(stamps, dtype=np.int64)
    bad = np.nonzero(np.diff(t) <= 0)[0]
    if bad.size:
        raise ValueError(f"{path}: IMU timestamps not increasing at data row {int(bad[0]) + 1}")
    v = np.asarray(vals)
    return ImuData(t, v[:, :3], v[:, 3:])


def time_offset(traj: Trajectory, imu: ImuData, max_offset_ns: int = 50_000_000,
                step_ns: int = 1_000_000) -> tuple[int, np.ndarray, np.ndarray]:
    """Best offset d (ns) such that |omega_real(t)| matches |omega_traj(t + d)|; returns (d, offsets, corr)."""
    lo, hi = traj.t0_ns + max_offset_ns, traj.t_end_ns - max_offset_ns
    m = (imu.stamps_ns >= lo) & (imu.stamps_ns <= hi)
    t = imu.stamps_ns[m]
    real = np.linalg.norm(imu.omega_S[m], axis=1)
    real = (real - real.mean()) / real.std()
    offsets = np.arange(-max_offset_ns, max_offset_ns + 1, step_ns, dtype=np.int64)
    corr = np.empty(len(offsets))
    for i, d in enumerate(offsets):
        s = np.linalg.norm(traj.body_rate(t + d), axis=1)
        corr[i] = np.mean(real * (s - s.mean()) / s.std())
    return int(offsets[np.argmax(corr)]), offsets, corr
