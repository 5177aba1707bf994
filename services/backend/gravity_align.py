"""Gravity alignment of a window that started moving (several cameras: the window has metric scale from the start).

A moving start takes gravity from the gyro-rotated accelerometer readings of the last ``static_window_s`` with the
velocity change over it taken as zero and the gyro bias unknown (services/backend/init.py): on EuRoC's flying starts
this tilts W by 1-3 deg. Held loosely, the tilt then wanders while vision and the IMU settle it over seconds and
bends the trajectory (the accelerometer bias trades against it); held firmly, it stays wrong. So the window holds it
firmly and, once it spans ``backend.moving_align_after_s`` of keyframes, measures it again from what the window now
knows, and turns the whole window once:

1. each keyframe's body pose relative to the oldest one (vision's, metric with stereo) and the IMU deltas between
   consecutive keyframes (pre-integrated) give the keyframes' velocities
   and gravity in the oldest keyframe's frame by the linear least squares of :func:`services.backend.mono_init.align`
   (its scale, which should come out 1, is the check; held at 1 when the window barely moved, as a drone standing
   with its rotors running, which fails the static test, does); the deltas take the window's gyro bias but a zero
   accelerometer bias, which the window's estimate has bent to fit its tilt;
2. the window (poses, velocities, landmarks) is rotated about the oldest keyframe's position by the smallest
   rotation that takes that gravity to -z of W (yaw kept), the velocities replaced by the alignment's, the
   accelerometer bias (which had absorbed the tilt) reset to zero, and the oldest state's prior reset there.

The published poses jump once by that rotation about the starting point (a few centimetres after a second of
flight).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, L, V, X

from services.backend.init import rotation_aligning
from services.backend.mono_init import align


@dataclass(frozen=True)
class GravityAlignment:
    rotation_deg: float     # how far the window was turned
    scale: float            # the alignment's free scale (1 for a consistent window)
    keyframes: int


def imu_deltas(pim, bias: gtsam.imuBias.ConstantBias, gravity: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """(dR (3,3), dp (3,), dv (3,), dt) of a pre-integration (gravity ``gravity`` [m/s^2] along -z, as
    services/backend/imu_factors.make_params sets it) re-expressed at ``bias`` (first order, gtsam's own
    correction), gravity removed: the motion the IMU felt, in the earlier body frame."""
    dt = pim.deltaTij()
    nav = pim.predict(gtsam.NavState(gtsam.Rot3(), np.zeros(3), np.zeros(3)), bias)
    g = np.array([0.0, 0.0, -gravity])
    return nav.attitude().matrix(), nav.position() - 0.5 * g * dt * dt, nav.velocity() - g * dt, dt


def gravity_in_window(values: gtsam.Values, states: list[int], pims: list, T_SC: np.ndarray, gravity: float,
                      min_travel_m: float = 0.0) -> tuple[np.ndarray, np.ndarray, float] | None:
    """(gravity (3,) in W as the window's poses and IMU deltas see it, velocities (K,3) in W, scale) for the
    keyframes ``states`` (oldest first; ``pims[k]`` the pre-integration from states[k] to states[k+1]); None when
    the alignment is implausible. The scale is solved for (a check: 1 for a consistent window) when the cameras
    travelled ``min_travel_m`` or more, else held at 1 (a body that stands or hovers shows gravity, not scale)."""
    T = [values.atPose3(X(s)).matrix() for s in states]
    R_WC0 = T[0][:3, :3] @ T_SC[:3, :3]
    T_C0W = np.linalg.inv(T[0] @ T_SC)
    T_C0S = [T_C0W @ Tk for Tk in T]
    R_0S = np.array([Tk[:3, :3] for Tk in T_C0S])
    c_0 = np.array([(Tk @ T_SC)[:3, 3] for Tk in T_C0S])  # camera centres in the oldest camera's frame
    # the window's gyro bias, but no accelerometer bias: held against a tilted gravity, the window's estimate of it
    # has absorbed the tilt (1.2 m/s^2 for 7 deg), which would hide it here
    deltas = [imu_deltas(p, gtsam.imuBias.ConstantBias(np.zeros(3), values.atConstantBias(B(s)).gyroscope()), gravity)
              for p, s in zip(pims, states[:-1])]
    travel = float(np.max(np.linalg.norm(c_0 - c_0[0], axis=1)))
    res = align(R_0S, c_0, T_SC[:3, 3], np.array([d[1] for d in deltas]), np.array([d[2] for d in deltas]),
                np.array([d[3] for d in deltas]), gravity, None if travel >= min_travel_m else 1.0)
    if res is None:
        return None
    scale, v_0, g_0 = res
    return R_WC0 @ g_0, v_0 @ R_WC0.T, scale


def turn_window(values: gtsam.Values, states: list[int], landmarks, R: np.ndarray, pivot: np.ndarray
                ) -> gtsam.Values:
    """``values`` with the poses of ``states``, their velocities and the ``landmarks`` rotated by ``R`` about
    ``pivot`` (a rigid motion of W: vision's residuals are unchanged)."""
    out = gtsam.Values(values)
    for s in states:
        Tk = values.atPose3(X(s)).matrix()
        Tn = np.eye(4)
        Tn[:3, :3], Tn[:3, 3] = R @ Tk[:3, :3], pivot + R @ (Tk[:3, 3] - pivot)
        out.update(X(s), gtsam.Pose3(Tn))
        out.update(V(s), R @ values.atVector(V(s)))
    for lm in landmarks:
        out.update(L(lm), pivot + R @ (values.atPoint3(L(lm)) - pivot))
    return out


def align_window(values: gtsam.Values, states: list[int], pims: list, T_SC: np.ndarray, gravity: float,
                 max_scale_error: float, min_travel_m: float = 0.0) -> tuple[gtsam.Values, GravityAlignment] | None:
    """The window turned so that the gravity it measures points along -z of W (see the module doc), with the
    alignment's velocities and a zero accelerometer bias; None when the alignment is implausible or its scale
    (solved for from ``min_travel_m`` of travel) is off by more than ``max_scale_error`` (relative)."""
    got = gravity_in_window(values, states, pims, T_SC, gravity, min_travel_m)
    if got is None or abs(got[2] - 1.0) > max_scale_error:
        return None
    g_W, v_W, scale = got
    R = rotation_aligning(g_W, [0.0, 0.0, -1.0])
    pivot = values.atPose3(X(states[0])).translation()
    landmarks = [int(gtsam.Symbol(k).index()) for k in values.keys() if gtsam.Symbol(k).chr() == ord("l")]
    out = turn_window(values, states, landmarks, R, pivot)
    for s, v in zip(states, v_W):
        out.update(V(s), R @ v)
        b = values.atConstantBias(B(s))
        out.update(B(s), gtsam.imuBias.ConstantBias(np.zeros(3), b.gyroscope()))
    angle = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))
    return out, GravityAlignment(angle, float(scale), len(states))
