"""The per-frame fast path as a transport-free process node: frontend/frame + sensors/imu + estimator/window ->
estimator/state for every frame (services/backend/odometry.py), so that no frame waits for the back end's keyframe
optimisation. The frontend's process runs it right after each frame is tracked
(services/frontend/process_node.py); it is a node of its own so that it can be driven alone (tests over Zenoh).

Published states are in the frame W' the loop closer moved the estimator's W to (the window's ``T_corr``); a
frame that cannot be tracked (stale, no IMU over its interval, bad arrays) is dropped, counted and logged. With
``backend.fast_path_waits_for_window`` (lockstep runs) a frame after a keyframe waits up to ``backend.imu_wait_s``
for that keyframe's window, so that a lockstep run over Zenoh gives what the in-process runner gives.
"""

from __future__ import annotations

import logging

import numpy as np

from shared.backlog import shed_backlog
from services.backend.loop.backend_loop import corrected_state
from services.backend.node import backend_cameras
from services.backend.odometry import FrameTracker
from services.backend.window_rules import keyframe_due
from shared import topics
from shared.dataflow import Emit, Input, ProcessNode, RejectedMessage
from shared.messages import EstimatorState, EstimatorWindow, FeatureFrame, Header, ImuSample

log = logging.getLogger("sigmaslam.odometry")


class OdometryNode(ProcessNode):
    """Per-frame state from the back end's newest window (``cfg``: the system config)."""

    name = "odometry"
    stage = "track"
    inputs = (
        Input(topics.FEATURES, "on_features", role="trigger", shed="shed", note="tracks of each frame"),
        Input(topics.IMU, "on_imu", wait_until_trigger_stamp=True, note="pre-integration from the keyframe"),
        Input(topics.WINDOW, "on_window", policy="latest", depth=2, wait_until_trigger_stamp=True,
              note="the back end's newest keyframe and landmarks (waited for only in lockstep runs)"),
    )
    outputs = (topics.STATE,)
    output_notes = {topics.STATE.key: "every frame"}

    def __init__(self, cfg, cameras) -> None:
        bc = cfg.backend
        self.bc = bc
        self.budget_ms, self.wait_s = bc.fast_path_budget_ms, bc.imu_wait_s
        self.tracker = FrameTracker(bc, backend_cameras(cameras))
        self.waits_for_window = bc.fast_path_waits_for_window
        self._expected_window_ns = -1  # the last frame the back end makes a keyframe of (its window is due)
        self._reset_pending = False
        self.dropped = 0
        self.seq = 0

    def wait_stamp(self, inp: Input, trigger_stamp_ns: int) -> int:
        if inp.topic is topics.WINDOW:
            return self._expected_window_ns if self.waits_for_window else -1
        return trigger_stamp_ns

    def shed(self, pending) -> tuple[list, int]:
        return shed_backlog(pending, self.bc.fast_path_max_backlog_frames, is_keyframe=lambda f: False)

    def on_imu(self, sample: ImuSample) -> None:
        self.tracker.add_imu(int(sample.header.stamp_ns), sample.omega_S, sample.acc_S)

    def on_window(self, msg: EstimatorWindow) -> None:
        if msg.status == "initialising":  # the back end has no state yet: nothing to anchor to
            return
        if msg.status == "reset":  # the back end restarted: its old window is gone, a new history starts
            self.tracker.reset()
            self._reset_pending = True
            return
        try:
            self.tracker.set_window(msg)
        except ValueError as exc:  # extrinsics for another rig: counted and logged by the runner
            raise RejectedMessage(f"estimator/window refused: {exc}") from None

    def _note_keyframe(self, frame: FeatureFrame) -> None:
        """Remember whether the back end will optimise its window at this frame (its rule, WindowedVioEstimator.
        wants_frame, seen from here: before its first window every frame, then keyframes and the longest gap)."""
        stamp = int(frame.header.stamp_ns)
        last = None if self.tracker.window is None else max(self._expected_window_ns, self.tracker.anchor_stamp_ns)
        if keyframe_due(stamp, bool(frame.is_keyframe), last, self.bc.max_keyframe_interval_s):
            self._expected_window_ns = stamp

    def on_features(self, frame: FeatureFrame) -> list[Emit]:
        stamp = int(frame.header.stamp_ns)
        self._note_keyframe(frame)
        try:
            st = self.tracker.track(stamp, frame.landmark_ids, frame.camera_index, frame.uv)
        except ValueError as exc:  # StaleFrame, ImuDataError, arrays that do not fit
            self.dropped += 1
            log.warning("feature frame %d dropped (%d so far): %s", stamp, self.dropped, exc)
            return []
        w = self.tracker.window  # its frame: 'W', or shared.map_folder.UNALIGNED_FRAME before a relocalisation
        header = Header(stamp_ns=stamp, seq=self.seq, frame_id=(w.header.frame_id or "W") if w is not None else "W")
        self.seq += 1
        if st is None:  # no window (yet, or since a back-end restart): say so (a lockstep player waits for an answer);
            # after a restart the first such state says 'reset' (consumers drop their history), as the back end's did
            status, self._reset_pending = ("reset" if self._reset_pending else "initialising"), False
            return [Emit(topics.STATE, EstimatorState(header=header, T_WS=np.eye(4), v_W=np.zeros(3),
                                                      gyro_bias=np.zeros(3), acc_bias=np.zeros(3),
                                                      covariance=np.full((15, 15), np.nan), status=status))]
        status = st.status
        state = EstimatorState(header=header, T_WS=np.ascontiguousarray(st.T_WS, np.float64),
                               v_W=np.asarray(st.v_W, np.float64), gyro_bias=np.asarray(st.gyro_bias, np.float64),
                               acc_bias=np.asarray(st.acc_bias, np.float64), covariance=np.full((15, 15), np.nan),
                               status=status)
        T = np.asarray(self.tracker.window.T_corr, float)
        if not np.allclose(T, np.eye(4)):
            state = corrected_state(state, T)
        return [Emit(topics.STATE, state)]
