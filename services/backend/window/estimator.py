"""Keyframe-window visual-inertial smoother (gtsam), causal output for every camera frame.

Design choices:

* **Window**: the last ``window_keyframes`` keyframes plus the latest frame; rebuilt from cached factors
  (:mod:`services.backend.window.observations`) and solved by Levenberg-Marquardt at keyframes. A non-keyframe frame (``motion_only_between_keyframes``, no per-frame
  covariance) solves only its own state against the window held fixed (:mod:`shared.vio.motion_only`) and is
  dropped, so the number of states is bounded. Outlier rejection and the marginal covariance run at keyframes (NaN
  for other frames unless ``compute_covariance``).
* **Marginalisation**: when the oldest keyframe leaves, the joint 15x15 marginal covariance of the next one's
  (pose, velocity, bias), taken from the full window, becomes a Gaussian prior on it at the current estimate. This
  keeps all past information about that state but drops its correlations with landmarks, so observations still in
  the window are counted twice: slightly over-confident, never rank deficient; a standard simplification.
* **Vision**: observations (distorted pixels) are undistorted by the camera model to normalised coordinates
  and enter ``GenericProjectionFactorCal3_S2`` with an identity calibration and ``body_P_sensor = T_SC_i``,
  noise sigma_px / f_i, wrapped in a Cauchy robust model (k in units of sigma). Normalised coordinates keep
  the distortion model out of the optimisation (any model the camera class supports works unchanged). With
  ``refine_extrinsics`` the T_SC_i are variables of the window instead (:mod:`services.backend.window.extrinsics`).
* **Landmarks** are added once seen in >= 2 window views (any cameras) with enough parallax, by linear
  triangulation, rejected on cheirality, depth range and reprojection error (:mod:`services.backend.window.triangulation`);
  after a keyframe's optimisation, observations with a reprojection error above the bound are removed, and the
  result carries the window's well-constrained landmarks (:meth:`WindowedVioEstimator.window_landmarks`).
* **One camera** (mono-inertial): a frame standing still relative to its keyframe gets a relative-pose and a
  zero-velocity factor (:mod:`services.backend.window.still`); a window that never stood still is rebuilt once from
  two-view geometry and a linear IMU alignment of scale, velocities and gravity (:mod:`services.backend.window.mono_init`).
* **No features**: the window keeps its IMU chain (keyframes still come at ``max_keyframe_interval_s``),
  the state is propagated by the IMU factors, status ``imu_only``.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, L, V, X

from services.backend.window import init as vio_init
from shared.vio.cameras import VioCamera
from services.backend.config import BackendConfig
from services.backend.window.extrinsics import ExtrinsicRefinement
from services.backend.window.frame_result import FrameResult, to_message_covariance
from services.backend.window.gravity_align import MovingStartAligner
from shared.vio.imu_factors import ImuBuffer, make_bias, make_params
from shared.vio.motion_only import optimise_latest
from services.backend.window.priors import WindowPrior, window_marginals
from services.backend.window.protocols import ExtraFactorSource, MarginalisationListener
from services.backend.window.mono_init import bootstrap as mono_bootstrap
from services.backend.window.observations import ObservationBook
from services.backend.window.time_offset import TimeOffsetEstimator, interval_residual
from shared.vio.vision_factors import ProjectionModel
from services.backend.window.graph import WindowGraph
from services.backend.window.window_api import WindowReadApi
from shared.vio.window_rules import VioInputError, keyframe_due, observation_arrays, schur_ordering, state_keys


class WindowedVioEstimator(WindowGraph, WindowReadApi):
    """Feed IMU with :meth:`add_imu` and frames with :meth:`process_frame` (in time order). ``extra_factors``:
    sources of factors for every window graph; ``on_marginalise``: told before the oldest keyframe leaves the
    window (services/backend/window/protocols.py). Others read the window through the read API
    (services/backend/window/window_api.py)."""

    def __init__(self, cfg: BackendConfig, cameras: list[VioCamera], imu_calib=None, *,
                 extra_factors: Sequence[ExtraFactorSource] = (),
                 on_marginalise: Sequence[MarginalisationListener] = ()) -> None:
        if not cameras:
            raise ValueError("the back end needs at least one camera")
        self.cfg = cfg
        self.cameras = list(cameras)
        kw = {}
        if imu_calib is not None:
            kw = {k: getattr(imu_calib, k) for k in ("gyro_noise_density", "accel_noise_density",
                                                     "gyro_random_walk", "accel_random_walk")}
        self.params = make_params(cfg, **kw)
        self.imu = ImuBuffer()
        self._vision = ProjectionModel(self.cameras, cfg.sigma_px, cfg.cauchy_k)
        self._T_SC = np.array([c.T_SC for c in self.cameras])
        self._focal = np.array([c.focal_px for c in self.cameras])
        # online extrinsic refinement (extrinsics.py): None when off
        self._extrinsics = ExtrinsicRefinement(cfg, len(cameras)) if cfg.refine_extrinsics else None
        self.time_offset = (TimeOffsetEstimator(cfg.time_offset_sigma_ms * 1e-3, cfg.time_offset_walk_ms * 1e-3,
                                                cfg.time_offset_max_ms * 1e-3) if cfg.estimate_time_offset else None)
        self.values = gtsam.Values()
        self.keyframes: list[int] = []        # state indices of the window's keyframes, oldest first
        self.stamps: dict[int, int] = {}
        self._imu_factors: dict[int, gtsam.NonlinearFactor] = {}  # keyed by the later state
        self._prior = WindowPrior()  # the oldest state's prior: factors, covariance (set by initialise), carries
        self._book = ObservationBook()  # observations, landmarks in the graph, their factors (observations.py)
        self._still: dict[int, list[gtsam.NonlinearFactor]] = {}  # one camera: factors of a still state (still.py)
        self.still_frames = 0
        # no more stand-still factors: a rig of several cameras without backend.still_stereo, or since it first moved
        self._still_over = len(self.cameras) > 1 and not cfg.still_stereo
        # one camera: until the window stood still once or was rebuilt by mono_init, vision has no metric hold
        self._mono_pending = len(self.cameras) == 1
        self.mono_bootstraps = 0
        self.mono_init_reason = ""  # why the last rebuild attempt failed
        self._next = 0
        self.initialised = False
        self.dropped_observations = 0
        self.failed_optimisations = 0
        self.held_marginals = 0  # window marginals computed with the landmarks held (priors.window_marginals)
        self.last_error = ""
        self._marginals: gtsam.Marginals | None = None
        self._first_frame_pending = False
        self._gravity = MovingStartAligner(cfg)  # a moving start's window is turned to its measured gravity
        self._extra_factors = tuple(extra_factors)
        self._on_marginalise = tuple(on_marginalise)

    # ---------------------------------------------------------------- input
    def add_imu(self, stamp_ns: int, omega_S: np.ndarray, acc_S: np.ndarray) -> None:
        self.imu.add(stamp_ns, omega_S, acc_S)

    def initialise(self, stamp_ns: int, R_WS: np.ndarray, v_W: np.ndarray, gyro_bias: np.ndarray,
                   acc_bias: np.ndarray, static: bool, p_W: np.ndarray | None = None) -> None:
        """Start the window with one state at ``stamp_ns`` (called automatically from IMU data if not before)."""
        c = self.cfg
        n = self._new_state(stamp_ns)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R_WS, np.zeros(3) if p_W is None else p_W
        self.values.insert(X(n), gtsam.Pose3(T))
        self.values.insert(V(n), np.asarray(v_W, float))
        self.values.insert(B(n), make_bias(gyro_bias, acc_bias))
        if static:
            self.reset_prior(n, c.prior_sigma_rot_rad, c.prior_sigma_vel_m_s, c.prior_sigma_gyro_bias)
        else:
            self.reset_prior(n, c.prior_sigma_tilt_moving_rad, c.prior_sigma_vel_moving_m_s,
                             c.prior_sigma_gyro_bias_moving)
        self.keyframes = [n]
        self._gravity.start(static, len(self.cameras))
        if self._extrinsics is not None:
            self._extrinsics.start(self.values, self._T_SC)
        self.initialised = True
        self._first_frame_pending = True  # the next frame at this stamp attaches to this state

    def _auto_initialise(self, stamp_ns: int) -> bool:
        t0 = stamp_ns - int(self.cfg.static_window_s * 1e9)
        st = np.array(self.imu.stamps_ns, np.int64)
        sel = (st >= t0) & (st <= stamp_ns)
        if len(st) == 0 or st[0] > t0 or sel.sum() < 10:
            return False
        res = vio_init.initialise(st[sel], np.array(self.imu.omega)[sel], np.array(self.imu.acc)[sel],
                                  self.cfg.static_gyro_std, self.cfg.static_acc_std, self.cfg.static_lowpass_s)
        self.initialise(stamp_ns, res.R_WS, res.v_W, res.gyro_bias, res.acc_bias, res.static)
        return True

    def _new_state(self, stamp_ns: int) -> int:
        n = self._next
        self._next += 1
        self.stamps[n] = int(stamp_ns)
        return n

    # ---------------------------------------------------------------- per frame
    def wants_frame(self, stamp_ns: int, is_keyframe: bool) -> bool:
        """Whether :meth:`process_frame` would make this frame a keyframe (or needs it to initialise): the frames the
        back-end service gives it; the others only the per-frame fast path tracks (services/frontend/odometry.py)."""
        last = self.stamps[self.keyframes[-1]] if self.initialised else None
        return self._first_frame_pending or keyframe_due(stamp_ns, is_keyframe, last, self.cfg.max_keyframe_interval_s)

    def process_frame(self, stamp_ns: int, landmark_ids: np.ndarray, camera_index: np.ndarray, uv: np.ndarray,
                      is_keyframe: bool = False) -> FrameResult | None:
        """Add one frame's observations, optimise the window, return the causal estimate (None before init)."""
        ids, cams, uv = self._validate(stamp_ns, landmark_ids, camera_index, uv)
        if not self.initialised:
            if not self._auto_initialise(stamp_ns):
                return None
            n = self.keyframes[-1]
        elif self._first_frame_pending and stamp_ns == self.stamps[self.keyframes[-1]]:
            n = self.keyframes[-1]
        else:
            n = self._add_state(stamp_ns)
        self._first_frame_pending = False
        self._add_observations(n, ids, cams, uv)
        last_kf = self.keyframes[-1]
        self._add_still(n, last_kf)
        keyframe = n == last_kf or keyframe_due(stamp_ns, is_keyframe, self.stamps[last_kf],
                                                self.cfg.max_keyframe_interval_s)
        if not keyframe and self.cfg.motion_only_between_keyframes and not self.cfg.compute_covariance:
            return self._motion_only_frame(n, last_kf)
        if self._mono_pending and keyframe:
            self._mono_rebuild(n)
        graph = self._solve_window(n, keyframe, last_kf)
        status = "tracking" if len(self._book.seen_at(n)) >= self.cfg.min_landmarks_tracking else "imu_only"
        result = self._result(n, self._covariance(graph, n, keyframe), status)
        if keyframe:
            result = dataclasses.replace(result, landmarks=self.window_landmarks())
        self._keep_or_drop(n, keyframe, last_kf)
        return result

    def _mono_rebuild(self, n: int) -> None:
        """One camera, a keyframe while the window has no metric hold: rebuilt from two-view geometry and the IMU
        (mono_init.py) unless it stood still."""
        c = self.cfg
        if self.still_frames:  # standing still anchored the state: no rebuild needed
            self._mono_pending = False
            return
        self.mono_init_reason = mono_bootstrap(self, n, c.mono_init_min_features, np.deg2rad(c.mono_init_parallax_deg),
                                               c.mono_init_ransac_px)
        if not self.mono_init_reason:
            self._mono_pending = False
            self._still.clear()  # only the speed priors of the wait: the rebuild knows the velocities
            self.mono_bootstraps += 1

    def _solve_window(self, n: int, keyframe: bool, last_kf: int) -> gtsam.NonlinearFactorGraph:
        """Triangulate, optimise the window (the IMU chain alone if that fails), read the refined extrinsics, reject
        outliers, and at a keyframe turn a moving start to its gravity and update the time offset; the graph."""
        self._triangulate_new(n)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(self.cfg.lm_max_iterations)
        params.setRelativeErrorTol(self.cfg.lm_relative_error_tol)
        try:
            graph = self._optimise(n, params)
        except RuntimeError as exc:  # e.g. an indeterminant system: fall back to the IMU chain alone
            self._note_failure(exc)
            self.forget_triangulations()
            graph = self._optimise(n, params)
        if self._extrinsics is not None:
            self._T_SC = self._extrinsics.read(self.values)
            self._vision.set_extrinsics(self._T_SC)
        # a non-keyframe state leaves the window after this frame, and its observations with it: rejection
        # (a pass over every observation of the window) is only worth it when the frame stays
        if (keyframe or self.cfg.reject_outliers_every_frame) and self._reject_outliers():
            graph = self._build_graph(n)
        if keyframe and n != last_kf and self._gravity.try_align(self, n):  # a moving start's window turned
            try:
                graph = self._optimise(n, params)
            except RuntimeError as exc:
                self._note_failure(exc)
                graph = self._build_graph(n)
        if keyframe and self.time_offset is not None and n != self.keyframes[-1]:  # time_offset.py
            e, g = interval_residual(self.values, self.imu, self.stamps, self.keyframes[-1], n)
            self.time_offset.update(e, g, np.radians(self.cfg.time_offset_rotation_sigma_deg))
        return graph

    def _covariance(self, graph: gtsam.NonlinearFactorGraph, n: int, keyframe: bool) -> np.ndarray:
        """The (15,15) marginal covariance of state ``n`` (with ``compute_covariance`` or at a keyframe; NaN
        otherwise or when the marginals fail), keeping the window's marginals for the read API."""
        self._marginals = None
        if not (self.cfg.compute_covariance or keyframe):
            return np.full((15, 15), np.nan)
        self._marginals, held = window_marginals(graph, self.values, self._book.in_graph,
                                                 self.cfg.marginals_landmark_sigma_m)
        self.held_marginals += held
        joint = self.joint_marginal(state_keys(n))
        if joint is None:
            self._marginals = None
            self.failed_optimisations += 1
            return np.full((15, 15), np.nan)
        return joint

    def _keep_or_drop(self, n: int, keyframe: bool, last_kf: int) -> None:
        """A new keyframe joins the window (the oldest marginalised beyond ``window_keyframes``); another frame's
        state leaves it."""
        if n != last_kf:
            if keyframe:
                self.keyframes.append(n)
                if len(self.keyframes) > self.cfg.window_keyframes:
                    self._marginalise_oldest()
            else:
                self._remove_state(n)
        self.imu.prune_before(self.stamps[self.keyframes[-1]])

    def _note_failure(self, exc: Exception) -> None:
        self.failed_optimisations += 1
        self.last_error = str(exc)

    def _optimise(self, n: int, params: gtsam.LevenbergMarquardtParams) -> gtsam.NonlinearFactorGraph:
        """The window's graph (newest state ``n``) built and optimised into ``values``; returns the graph."""
        graph = self._build_graph(n)
        params.setOrdering(schur_ordering(self._book.in_graph, self.stamps,
                                          () if self._extrinsics is None else self._extrinsics.keys))
        self.values = gtsam.LevenbergMarquardtOptimizer(graph, self.values, params).optimize()
        return graph

    def _motion_only_frame(self, n: int, k: int) -> FrameResult:
        """Non-keyframe: solve the newest state alone against the fixed window, report it, drop it."""
        lms = self._book.seen_at(n)
        seen = [(self.values.atPoint3(L(lm)), c, xy) for lm in lms for c, xy in self._book.by_landmark[lm][n]]
        pts = self._vision.fixed_points(np.array([p for p, _, _ in seen]).reshape(-1, 3),
                                        np.array([xy for _, _, xy in seen]).reshape(-1, 2), [c for _, c, _ in seen])
        try:
            upd = optimise_latest(self.values, n, [self._imu_factors[n], *self._still.get(n, [])], pts,
                                  self.cfg.lm_max_iterations, relative_tol=self.cfg.lm_relative_error_tol)
            self.values.update(upd)
        except RuntimeError as exc:  # keep the IMU prediction
            self._note_failure(exc)
        status = "tracking" if len(lms) >= self.cfg.min_landmarks_tracking else "imu_only"
        result = self._result(n, np.full((15, 15), np.nan), status)
        self._remove_state(n)
        self.imu.prune_before(self.stamps[self.keyframes[-1]])
        return result

    def _validate(self, stamp_ns, landmark_ids, camera_index, uv):
        ids, cams, uv, ok = observation_arrays(landmark_ids, camera_index, uv, len(self.cameras))
        latest = max(self.stamps.values()) if self.stamps else None
        if latest is not None and (stamp_ns < latest or (stamp_ns == latest and not self._first_frame_pending)):
            raise VioInputError(f"frame stamp {stamp_ns} ns is not after the previous frame")
        self.dropped_observations += int((~ok).sum())
        return ids[ok], cams[ok], uv[ok]

    def _result(self, n: int, cov: np.ndarray, status: str) -> FrameResult:
        T = self.values.atPose3(X(n)).matrix()
        bias = self.values.atConstantBias(B(n))
        kfs = list(self.keyframes)
        return FrameResult(
            stamp_ns=self.stamps[n], T_WS=T, v_W=np.asarray(self.values.atVector(V(n))),
            gyro_bias=np.asarray(bias.gyroscope()), acc_bias=np.asarray(bias.accelerometer()),
            covariance=to_message_covariance(cov, T[:3, :3]), status=status,
            keyframe_ids=np.array(kfs, np.int64), keyframe_stamps_ns=np.array([self.stamps[k] for k in kfs], np.int64),
            keyframe_T_WS=np.array([self.values.atPose3(X(k)).matrix() for k in kfs]),
            num_landmarks=len(self._book.in_graph), T_SC=None if self._extrinsics is None else self._T_SC.copy(),
            time_offset_s=0.0 if self.time_offset is None else self.time_offset.td)

    # ---------------------------------------------------------------- writes (mono_init's rebuild)
    def reset_prior(self, state: int, tilt_sigma: float, vel_sigma: float, gyro_bias_sigma: float) -> None:
        """The window's prior: independent priors on ``state`` (its oldest) at its current estimate, with these
        roll/pitch [rad], velocity [m/s] and gyro bias [rad/s] sigmas and the config's yaw, position and
        accelerometer bias sigmas; its covariance is the one carried when marginals fail."""
        c = self.cfg
        pose_sig = np.array([tilt_sigma, tilt_sigma, c.prior_sigma_rot_rad] + [c.prior_sigma_pos_m] * 3)
        bias_sig = np.array([c.prior_sigma_acc_bias] * 3 + [gyro_bias_sigma] * 3)
        self._prior.reset(self.values, state, pose_sig, vel_sigma, bias_sig)
