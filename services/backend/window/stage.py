"""The keyframe window as the back end's stage (:class:`WindowStage`): the feature frames the estimator takes
through its solve into the messages the back end publishes (``estimator/window`` for the fast path,
``estimator/keyframes``, ``estimator/landmarks``), and those messages from its per-frame result."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from services.backend.window.estimator import WindowedVioEstimator
from services.backend.window.frame_result import FrameResult
from shared.messages import EstimatorState, EstimatorWindow, FeatureFrame, Header, ImuSample, Keyframes, Landmarks
from shared.vio.imu_factors import ImuDataError
from shared.vio.states import placeholder_state
from shared.vio.window_rules import VioInputError

log = logging.getLogger("sigmaslam.backend")


def state_message(result: FrameResult, seq: int) -> EstimatorState:
    """``estimator/state`` for one frame (header.frame_id = 'W')."""
    return EstimatorState(
        header=Header(stamp_ns=int(result.stamp_ns), seq=int(seq), frame_id="W"),
        T_WS=np.ascontiguousarray(result.T_WS, np.float64), v_W=np.asarray(result.v_W, np.float64),
        gyro_bias=np.asarray(result.gyro_bias, np.float64), acc_bias=np.asarray(result.acc_bias, np.float64),
        covariance=np.ascontiguousarray(result.covariance, np.float64), status=result.status)


def keyframes_message(result: FrameResult, seq: int) -> Keyframes:
    """``estimator/keyframes``: the window's keyframe poses after this frame's optimisation."""
    return Keyframes(
        header=Header(stamp_ns=int(result.stamp_ns), seq=int(seq), frame_id="W"),
        ids=np.asarray(result.keyframe_ids, np.int64), stamps_ns=np.asarray(result.keyframe_stamps_ns, np.int64),
        T_WS=np.ascontiguousarray(result.keyframe_T_WS, np.float64).reshape(-1, 4, 4))


def landmarks_message(result: FrameResult, seq: int) -> Landmarks | None:
    """``estimator/landmarks`` after a keyframe's optimisation (None for a frame that is no keyframe)."""
    lm = result.landmarks
    if lm is None:
        return None
    return Landmarks(
        header=Header(stamp_ns=int(result.stamp_ns), seq=int(seq), frame_id="W"),
        ids=np.asarray(lm.ids, np.int64), p_W=np.ascontiguousarray(lm.p_W, np.float64).reshape(-1, 3),
        num_observations=np.asarray(lm.num_observations, np.int32), last_seen_ns=np.asarray(lm.last_seen_ns, np.int64))


class WindowStage:
    """The estimator's per-frame path as messages. ``restarted``: after a supervisor restart the first state says
    'reset' (consumers drop the poses of before), then the window initialises from scratch."""

    def __init__(self, estimator: WindowedVioEstimator, restarted: bool = False) -> None:
        self.estimator = estimator
        self.restarted = restarted
        self.dropped = 0
        self.seq = 0
        self.landmarks: Landmarks | None = None  # of the last keyframe processed, until take_landmarks()
        self.last_result: FrameResult | None = None  # the estimator's raw result of the last frame processed

    def wants(self, frame: FeatureFrame) -> bool:
        """Whether the window takes ``frame`` (a keyframe, or the longest gap reached: the estimator's rule)."""
        return self.estimator.wants_frame(int(frame.header.stamp_ns), bool(frame.is_keyframe))

    def add_imu(self, sample: ImuSample) -> None:
        self.estimator.add_imu(int(sample.header.stamp_ns), sample.omega_S, sample.acc_S)

    def process(self, frame: FeatureFrame) -> tuple[EstimatorState, Keyframes | None] | None:
        """The frame's state (in W) and, after a keyframe's optimisation, the window's keyframes; None for a frame
        the estimator refuses (bad arrays, time going backwards, IMU gap: dropped, counted and logged)."""
        msgs = self._process(frame)
        if msgs is not None and self.restarted:
            self.restarted = False
            log.warning("back end restarted: state history lost, re-initialising (status 'reset' at %d)",
                        msgs[0].header.stamp_ns)
            msgs = (dataclasses.replace(msgs[0], status="reset"), msgs[1])
        return msgs

    def _process(self, frame: FeatureFrame) -> tuple[EstimatorState, Keyframes | None] | None:
        stamp = int(frame.header.stamp_ns)
        try:
            res = self.estimator.process_frame(stamp, frame.landmark_ids, frame.camera_index, frame.uv,
                                               bool(frame.is_keyframe))
        except (VioInputError, ImuDataError) as exc:
            self.dropped += 1
            log.warning("feature frame %d dropped (%d so far): %s", stamp, self.dropped, exc)
            return None
        if res is None:  # not initialised yet (needs IMU before the first frame): say so, for lockstep players
            msg = placeholder_state(Header(stamp_ns=stamp, seq=self.seq, frame_id="W"), "initialising")
            self.seq += 1
            return msg, None
        self.last_result = res
        msgs = state_message(res, self.seq), keyframes_message(res, self.seq)
        self.landmarks = landmarks_message(res, self.seq)
        self.seq += 1
        return msgs

    def take_landmarks(self) -> Landmarks | None:
        """estimator/landmarks of the last frame processed if it was a keyframe (once)."""
        msg, self.landmarks = self.landmarks, None
        return msg

    def window_message(self, state: EstimatorState, T_corr: np.ndarray | None) -> EstimatorWindow:
        """estimator/window after the frame that gave ``state`` (its status; the pose from the estimator's own
        result, in W): the newest keyframe and the window's landmarks for the fast path; ``T_corr``: the loop
        closer's correction T_W'W of the published frame (None: none)."""
        res = self.last_result
        if state.status in ("initialising", "reset") or res is None:  # no state to anchor to: status alone
            return EstimatorWindow(header=state.header, T_WS=np.eye(4), v_W=np.zeros(3), gyro_bias=np.zeros(3),
                                   acc_bias=np.zeros(3), T_corr=np.eye(4), landmark_ids=np.zeros(0, np.int64),
                                   p_W=np.zeros((0, 3)),
                                   status="reset" if state.status == "reset" else "initialising")
        ids, p_W = self.estimator.window_points()
        return EstimatorWindow(header=state.header, T_WS=np.ascontiguousarray(res.T_WS, np.float64),
                               v_W=np.asarray(res.v_W, np.float64), gyro_bias=np.asarray(res.gyro_bias, np.float64),
                               acc_bias=np.asarray(res.acc_bias, np.float64),
                               T_corr=np.eye(4) if T_corr is None else np.ascontiguousarray(T_corr, np.float64),
                               landmark_ids=ids, p_W=np.ascontiguousarray(p_W, np.float64),
                               T_SC=np.zeros((0, 4, 4)) if res.T_SC is None else np.ascontiguousarray(res.T_SC),
                               time_offset_s=float(res.time_offset_s), status=state.status)
