"""Initialisation of the body state from IMU data: gravity direction, gyro bias, velocity.

* **Static start** (gyro and accelerometer standard deviations below thresholds over the window): the mean
  specific force is ``-R_WS^T g_W``, so it gives roll and pitch; the mean gyro reading is the gyro bias;
  velocity is zero.
* **Moving start**: the gyro readings are integrated to rotate every accelerometer sample into the body frame
  S0 at the window start; their time average is ``R_W0^T (Delta v_W / T - g_W)``. With the velocity change
  over the window known (from vision, argument ``delta_v_S0``) it is removed exactly; without it, it is taken
  as zero, which errs by ``atan(|Delta v| / (T g))`` (0.6 deg for 0.2 m/s over 2 s). The windowed smoother
  then refines roll/pitch, velocity and biases jointly with vision (the first state's prior is loose in
  roll/pitch for a moving start).

Yaw is unobservable: the world frame W takes the yaw of the body at initialisation (minimal rotation that
takes the measured "up" to +z of W).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

class InitialisationError(ValueError):
    """Not enough or unusable IMU data to initialise."""


@dataclass(frozen=True)
class InitResult:
    R_WS: np.ndarray      # (3,3) body orientation at the window end
    v_W: np.ndarray       # (3,) velocity [m/s]
    gyro_bias: np.ndarray  # (3,) [rad/s]
    acc_bias: np.ndarray   # (3,) [m/s^2]
    static: bool


def rotation_aligning(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation R with R @ a_hat = b_hat."""
    a = np.asarray(a, float) / np.linalg.norm(a)
    b = np.asarray(b, float) / np.linalg.norm(b)
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(np.dot(a, b))
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        perp = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        return gtsam.Rot3.Expmap(np.pi * perp / np.linalg.norm(perp)).matrix()
    return gtsam.Rot3.Expmap(axis / s * np.arctan2(s, c)).matrix()


def _check(stamps_ns: np.ndarray, omega_S: np.ndarray, acc_S: np.ndarray) -> None:
    if len(stamps_ns) < 10:
        raise InitialisationError(f"need at least 10 IMU samples to initialise, got {len(stamps_ns)}")
    if omega_S.shape != (len(stamps_ns), 3) or acc_S.shape != (len(stamps_ns), 3):
        raise InitialisationError(f"IMU arrays of shape {omega_S.shape}, {acc_S.shape} for {len(stamps_ns)} stamps")
    if np.any(np.diff(stamps_ns) <= 0):
        raise InitialisationError("IMU stamps are not strictly increasing")


def block_means(stamps_ns: np.ndarray, x: np.ndarray, block_s: float) -> np.ndarray:
    """Means of ``x`` (N, 3) over consecutive blocks of ``block_s`` seconds (a low-pass; the whole when shorter)."""
    if block_s <= 0:
        return np.asarray(x, float)
    idx = ((np.asarray(stamps_ns, np.int64) - int(stamps_ns[0])) // int(block_s * 1e9)).astype(np.int64)
    counts = np.bincount(idx)
    sums = np.stack([np.bincount(idx, weights=x[:, k]) for k in range(x.shape[1])], 1)
    return sums[counts > 0] / counts[counts > 0, None]


def is_static(omega_S: np.ndarray, acc_S: np.ndarray, gyro_std_max: float, acc_std_max: float,
              stamps_ns: np.ndarray | None = None, lowpass_s: float = 0.0) -> bool:
    """True when the per-axis standard deviations stay below the thresholds; with ``stamps_ns`` and ``lowpass_s``
    > 0, of the readings averaged over blocks of ``lowpass_s`` (motor vibration of a MAV standing on the ground
    is not motion: EuRoC's raw gyro std is 0.02-0.06 rad/s there, its 50 ms means' 0.002-0.006)."""
    if stamps_ns is not None and lowpass_s > 0:
        omega_S, acc_S = block_means(stamps_ns, omega_S, lowpass_s), block_means(stamps_ns, acc_S, lowpass_s)
        if len(omega_S) < 3:
            return False
    return bool(np.max(np.std(omega_S, axis=0)) < gyro_std_max and np.max(np.std(acc_S, axis=0)) < acc_std_max)


def static_init(stamps_ns: np.ndarray, omega_S: np.ndarray, acc_S: np.ndarray) -> InitResult:
    omega_S, acc_S = np.asarray(omega_S, float), np.asarray(acc_S, float)
    _check(np.asarray(stamps_ns), omega_S, acc_S)
    up_S = acc_S.mean(axis=0)
    return InitResult(R_WS=rotation_aligning(up_S, [0.0, 0.0, 1.0]), v_W=np.zeros(3),
                      gyro_bias=omega_S.mean(axis=0), acc_bias=np.zeros(3), static=True)


def moving_init(stamps_ns: np.ndarray, omega_S: np.ndarray, acc_S: np.ndarray,
                delta_v_S0: np.ndarray | None = None, gyro_bias: np.ndarray | None = None,
                v_W_end: np.ndarray | None = None) -> InitResult:
    """Gravity from gyro-rotated accelerometer readings averaged over the window (see module doc).

    ``delta_v_S0``: velocity change over the window in the first body frame [m/s] if known (vision);
    ``v_W_end``: velocity at the window end if known (else zero, with a loose prior downstream).
    """
    stamps_ns = np.asarray(stamps_ns, np.int64)
    omega_S, acc_S = np.asarray(omega_S, float), np.asarray(acc_S, float)
    _check(stamps_ns, omega_S, acc_S)
    bg = np.zeros(3) if gyro_bias is None else np.asarray(gyro_bias, float)
    dts = np.diff(stamps_ns) * 1e-9
    R = np.eye(3)
    f_sum = np.zeros(3)
    for k, dt in enumerate(dts):
        w = 0.5 * (omega_S[k] + omega_S[k + 1]) - bg
        R_next = R @ gtsam.Rot3.Expmap(w * dt).matrix()
        f_sum += 0.5 * (R @ acc_S[k] + R_next @ acc_S[k + 1]) * dt
        R = R_next
    T = float(dts.sum())
    up_S0 = f_sum / T
    if delta_v_S0 is not None:
        up_S0 = up_S0 - np.asarray(delta_v_S0, float) / T
    R_W0 = rotation_aligning(up_S0, [0.0, 0.0, 1.0])
    v = np.zeros(3) if v_W_end is None else np.asarray(v_W_end, float)
    return InitResult(R_WS=R_W0 @ R, v_W=v, gyro_bias=bg, acc_bias=np.zeros(3), static=False)


def initialise(stamps_ns: np.ndarray, omega_S: np.ndarray, acc_S: np.ndarray, gyro_std_max: float,
               acc_std_max: float, lowpass_s: float = 0.0) -> InitResult:
    """Static initialisation when the window is still (:func:`is_static`), moving initialisation otherwise."""
    omega_S, acc_S = np.asarray(omega_S, float), np.asarray(acc_S, float)
    _check(np.asarray(stamps_ns), omega_S, acc_S)
    if is_static(omega_S, acc_S, gyro_std_max, acc_std_max, np.asarray(stamps_ns, np.int64), lowpass_s):
        return static_init(stamps_ns, omega_S, acc_S)
    return moving_init(stamps_ns, omega_S, acc_S)
