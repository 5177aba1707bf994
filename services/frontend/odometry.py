"""The per-frame fast path: every camera frame's state from the IMU and its tracks, against the back end's latest
window held fixed, so that no frame waits for a keyframe's window optimisation.

The back end (services/backend/window/estimator.py) optimises its keyframe window only at keyframes; after each it
publishes the newest keyframe's state and the window's landmarks (``estimator/window``). For every frame, this
tracker pre-integrates the IMU from that keyframe to the frame, predicts the state, and solves the frame's pose,
velocity and bias alone against the IMU factor from the keyframe and the reprojection factors of the landmarks the
window has triangulated, keyframe and landmarks pinned at the window's estimate (shared/vio/motion_only.py,
the solve the estimator uses between keyframes; for ``backend.fast_path_settle_s`` after the first window the
keyframe's velocity and biases are solved too, held by priors, since a window just initialised has not settled them).
A keyframe's own state therefore comes from this solve too, before
the window is optimised; later frames use the new window as soon as it arrives (in a live run a frame or two
after the keyframe; in stamp order, before the next frame). Covariance is not computed here (NaN).
"""

from __future__ import annotations

import copy
import dataclasses

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X

from shared.vio.cameras import VioCamera
from shared.vio.imu_factors import ImuBuffer, imu_factor, make_bias, make_params, predict
from shared.vio.motion_only import optimise_latest
from shared.vio.vision_factors import ProjectionModel
from shared.vio.window_rules import observation_arrays
from shared.messages import EstimatorWindow
from shared.vio.config import VioConfig

KEYFRAME, FRAME = 0, 1  # state indices of the pinned keyframe and the frame being solved


class StaleFrame(ValueError):
    """A frame older than the window's newest keyframe (it cannot be predicted forward from it)."""


@dataclasses.dataclass(frozen=True)
class TrackedState:
    """One frame's state in the estimator's frame W (before any loop correction)."""

    stamp_ns: int
    T_WS: np.ndarray
    v_W: np.ndarray
    gyro_bias: np.ndarray
    acc_bias: np.ndarray
    status: str  # 'tracking' or 'imu_only'
    landmarks: int  # window landmarks observed in the frame
    solved: bool  # False: the solve failed and the IMU prediction is reported


class FrameTracker:
    """Feed IMU with :meth:`add_imu`, the back end's windows with :meth:`set_window`, frames with :meth:`track`."""

    def __init__(self, cfg: VioConfig, cameras: list[VioCamera]) -> None:
        if not cameras:
            raise ValueError("the fast path needs at least one camera")
        self.cfg = cfg
        self.params = make_params(cfg)
        self.imu = ImuBuffer()
        self.vision = ProjectionModel(cameras, cfg.sigma_px, cfg.cauchy_k)
        self.window: EstimatorWindow | None = None
        self._lm_ids = np.zeros(0, np.int64)  # the window's landmark ids, sorted
        self._lm_p = np.zeros((0, 3))  # their positions in W, in that order
        self.failed_solves = 0
        # the anchor's pre-integration, extended frame by frame up to the last IMU sample used (a frame integrates
        # only the samples since the previous one, however old the anchor)
        self._pim: gtsam.PreintegratedCombinedMeasurements | None = None
        self._pim_end_ns = -1
        self._first_anchor_ns: int | None = None  # the first window's stamp (since the start or a reset)
        # while the window is young (backend.fast_path_settle_s): the priors on its anchor's velocity and bias
        self._settle_v = gtsam.noiseModel.Isotropic.Sigma(3, cfg.fast_path_settle_velocity_sigma)
        self._settle_b = gtsam.noiseModel.Diagonal.Sigmas(np.array(
            [cfg.fast_path_settle_acc_bias_sigma] * 3 + [cfg.fast_path_settle_gyro_bias_sigma] * 3))

    def add_imu(self, stamp_ns: int, omega_S: np.ndarray, acc_S: np.ndarray) -> None:
        self.imu.add(stamp_ns, omega_S, acc_S)

    def set_window(self, msg: EstimatorWindow) -> bool:
        """Use ``msg`` as the anchor of the next frames; False (ignored) for one older than the current anchor."""
        if self.window is not None and msg.header.stamp_ns < self.window.header.stamp_ns:
            return False
        if len(msg.T_SC):  # the back end refines the extrinsics: track with its newest (ValueError: another rig's)
            self.vision.set_extrinsics(msg.T_SC)
        self.window = msg
        if self._first_anchor_ns is None:
            self._first_anchor_ns = int(msg.header.stamp_ns)
        ids = np.asarray(msg.landmark_ids, np.int64)
        order = np.argsort(ids, kind="stable")
        self._lm_ids, self._lm_p = ids[order], np.asarray(msg.p_W, float).reshape(-1, 3)[order]
        self.imu.prune_before(int(msg.header.stamp_ns))
        self._pim, self._pim_end_ns = None, -1
        return True

    def reset(self) -> None:
        """Forget the window (the back end restarted: its next windows start a new history)."""
        self.window, self._lm_ids, self._lm_p = None, np.zeros(0, np.int64), np.zeros((0, 3))
        self._pim, self._pim_end_ns, self._first_anchor_ns = None, -1, None

    def _preintegrate(self, bias, k_ns: int, stamp_ns: int) -> gtsam.PreintegratedCombinedMeasurements:
        """Pre-integration from the anchor ``k_ns`` to ``stamp_ns``, from the running one when it can be extended."""
        last = self.imu.last_stamp_at_or_before(stamp_ns)
        if self._pim is None or self._pim_end_ns > stamp_ns:  # a new anchor (or a frame before the running end)
            self._pim, self._pim_end_ns = gtsam.PreintegratedCombinedMeasurements(self.params, bias), k_ns
        if last is not None and last > self._pim_end_ns:
            self.imu.integrate_into(self._pim, bias, self._pim_end_ns, last)
            self._pim_end_ns = last
        pim = copy.copy(self._pim)
        if stamp_ns > self._pim_end_ns:  # the piece after the last sample (none when the frame has a sample's stamp)
            self.imu.integrate_into(pim, bias, self._pim_end_ns, stamp_ns)
        return pim

    @property
    def anchor_stamp_ns(self) -> int | None:
        return None if self.window is None else int(self.window.header.stamp_ns)

    def track(self, stamp_ns: int, landmark_ids: np.ndarray, camera_index: np.ndarray, uv: np.ndarray
              ) -> TrackedState | None:
        """The frame's state (None while no window has come); raises :class:`StaleFrame` for a frame before the
        anchor, ``VioInputError`` for arrays that disagree and ``ImuDataError`` when the IMU does not cover the
        interval."""
        w = self.window
        if w is None:
            return None
        k_ns = int(w.header.stamp_ns)
        if stamp_ns < k_ns:
            raise StaleFrame(f"frame {stamp_ns} ns is older than the window's newest keyframe {k_ns} ns")
        ids, cams, uv, usable = observation_arrays(landmark_ids, camera_index, uv, len(self.vision.cameras))
        row = np.minimum(np.searchsorted(self._lm_ids, ids), max(len(self._lm_ids) - 1, 0))
        known = usable & (self._lm_ids[row] == ids) if len(self._lm_ids) else np.zeros(len(ids), bool)
        n_lms = len(np.unique(ids[known]))  # window landmarks seen (a landmark may be seen by several cameras)
        status = "tracking" if n_lms >= self.cfg.min_landmarks_tracking else "imu_only"
        if stamp_ns == k_ns:  # the keyframe itself: the window's estimate
            return TrackedState(stamp_ns, np.asarray(w.T_WS, float), np.asarray(w.v_W, float),
                                np.asarray(w.gyro_bias, float), np.asarray(w.acc_bias, float), status, n_lms, True)
        bias = make_bias(w.gyro_bias, w.acc_bias)
        pim = self._preintegrate(bias, k_ns, stamp_ns)
        T, v = predict(pim, np.asarray(w.T_WS, float), np.asarray(w.v_W, float), bias)
        values = gtsam.Values()
        values.insert(X(KEYFRAME), gtsam.Pose3(np.asarray(w.T_WS, float)))
        values.insert(V(KEYFRAME), np.asarray(w.v_W, float))
        values.insert(B(KEYFRAME), bias)
        values.insert(X(FRAME), gtsam.Pose3(T))
        values.insert(V(FRAME), np.asarray(v, float))
        values.insert(B(FRAME), bias)
        xy = self.vision.undistort(cams[known], uv[known])
        pts = self.vision.fixed_points(self._lm_p[row[known]], xy, cams[known])
        factors = [imu_factor(pim, (X(KEYFRAME), V(KEYFRAME), B(KEYFRAME)), (X(FRAME), V(FRAME), B(FRAME)))]
        also = []
        if self._first_anchor_ns is not None and k_ns - self._first_anchor_ns < self.cfg.fast_path_settle_s * 1e9:
            # a young window: its velocity and bias held by priors, not pinned
            factors += [gtsam.PriorFactorVector(V(KEYFRAME), np.asarray(w.v_W, float), self._settle_v),
                        gtsam.PriorFactorConstantBias(B(KEYFRAME), bias, self._settle_b)]
            also = [V(KEYFRAME), B(KEYFRAME)]
        solved = True
        try:
            values.update(optimise_latest(values, FRAME, factors, pts, self.cfg.lm_max_iterations, also=tuple(also),
                                          relative_tol=self.cfg.lm_relative_error_tol))
        except RuntimeError:  # keep the IMU prediction
            self.failed_solves += 1
            solved = False
        b = values.atConstantBias(B(FRAME))
        return TrackedState(stamp_ns, values.atPose3(X(FRAME)).matrix(), np.asarray(values.atVector(V(FRAME))),
                            np.asarray(b.gyroscope()), np.asarray(b.accelerometer()), status, n_lms, solved)
