"""Gravity alignment of a window that started moving (several cameras: the window has metric scale from the start).

A moving start takes gravity from the gyro-rotated accelerometer readings of the last ``static_window_s`` with the
velocity change over it taken as zero and the gyro bias unknown (services/backend/window/init.py): on EuRoC's flying starts
this tilts W by 1-3 deg. Held loosely, the tilt then wanders while vision and the IMU settle it over seconds and
bends the trajectory (the accelerometer bias trades against it); held firmly, it stays wrong. So the window holds it
firmly and, once it spans ``backend.moving_align_after_s`` of keyframes, measures it again from what the window now
knows, and turns the whole window once:

1. each keyframe's body pose relative to the oldest one (vision's, metric with stereo) and the IMU deltas between
   consecutive keyframes (pre-integrated) give the keyframes' velocities
   and gravity in the oldest keyframe's frame by the linear least squares of :func:`services.backend.window.mono_init.align`
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

import logging
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, L, V, X

from services.backend.window.init import rotation_aligning
from services.backend.window.mono_init import align

log = logging.getLogger("sigmaslam.backend")


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
    """``values`` with the poses of ``states`` and the ``landmarks`` rotated by ``R`` about ``pivot`` (a rigid motion
    of W: vision's residuals are unchanged; the velocities are the caller's to set)."""
    out = gtsam.Values(values)
    for s in states:
        Tk = values.atPose3(X(s)).matrix()
        Tn = np.eye(4)
        Tn[:3, :3], Tn[:3, 3] = R @ Tk[:3, :3], pivot + R @ (Tk[:3, 3] - pivot)
        out.update(X(s), gtsam.Pose3(Tn))
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


class MovingStartAligner:
    """When a window's gravity alignment is due, and what came of it: started by the estimator's initialisation,
    tried at each keyframe while pending (:meth:`try_align`), done once or given up."""

    def __init__(self, cfg) -> None:
        self.cfg = cfg  # BackendConfig
        self.pending = False
        self.result: GravityAlignment | None = None
        self.failures = 0

    def start(self, static: bool, n_cameras: int) -> None:
        """A new window: due after a moving start of a rig of several cameras (mono_init rebuilds one camera's)."""
        self.pending = not static and n_cameras > 1 and self.cfg.moving_align_after_s > 0

    def try_align(self, est, n: int) -> bool:
        """At keyframe ``n`` (about to join the window of ``est``, a WindowedVioEstimator): the window turned to the
        gravity it measures and its oldest state's prior reset there, when due (the keyframes span
        ``moving_align_after_s``, or fill the window before that: keyframes every 0.1 s span 0.8 s in 8, and the
        oldest would be marginalised with the tilt it has). True when it was: the caller optimises again."""
        c = self.cfg
        if not self.pending:
            return False
        states = [*est.keyframes, n]
        span_s = (est.stamps[n] - est.stamps[states[0]]) * 1e-9
        if len(states) < 4 or (span_s < c.moving_align_after_s and len(est.keyframes) < c.window_keyframes):
            return False
        stereo = sum(len({cam for cam, _ in obs}) > 1 for obs in est.observations_of(n).values())
        if stereo < c.moving_align_min_stereo:  # cameras that do not overlap: no metric hold of vision's own, so
            self.pending = False                # the window's positions follow the IMU and show no tilt to align
            return False
        got = align_window(est.values, states, [est.imu_factor_to(s).preintegratedMeasurements() for s in states[1:]],
                           est.T_SC[0], c.gravity_m_s2, c.moving_align_max_scale_error, c.moving_align_min_travel_m)
        if got is None:
            self.failures += 1
            log.info("moving start: the window's gravity alignment was refused (implausible, or its scale off by "
                     "more than %.0f %%)", 100 * c.moving_align_max_scale_error)
            self.pending = span_s < 3 * c.moving_align_after_s  # else keep the window as it is
            return False
        est.values, self.result = got
        self.pending = False
        log.info("moving start: window turned %.2f deg to the gravity its %d keyframes measure (scale %.3f)",
                 self.result.rotation_deg, self.result.keyframes, self.result.scale)
        est.reset_prior(states[0], c.prior_sigma_tilt_aligned_rad, c.prior_sigma_vel_moving_m_s,
                        c.prior_sigma_gyro_bias_moving)
        return True
