"""Messages from the estimator's per-frame result (what the service publishes)."""

from __future__ import annotations

import numpy as np

from services.backend.frame_result import FrameResult
from shared.messages import EstimatorState, Header, Keyframes, Landmarks


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
