"""The per-frame fast path as a collaborator of the frontend node: tracks + sensors/imu + estimator/window ->
every frame's estimator/state (the solve: services/frontend/odometry.py), so that no frame waits for the back end's
keyframe optimisation.

Published states are in the frame W' the loop closer moved the estimator's W to (the window's ``T_corr``); a frame
that cannot be tracked (stale, no IMU over its interval, bad arrays) is dropped, counted and logged. With
``backend.fast_path_waits_for_window`` (lockstep runs) a frame after a keyframe waits up to ``backend.imu_wait_s``
for that keyframe's window (:meth:`FastPath.window_stamp`), so that a lockstep run over Zenoh gives what the
in-process runner gives.
"""

from __future__ import annotations

import logging

import numpy as np

from services.frontend.odometry import FrameTracker
from shared.dataflow import RejectedMessage
from shared.messages import EstimatorState, EstimatorWindow, FeatureFrame, Header, ImuSample
from shared.vio.cameras import rig_cameras
from shared.vio.config import VioConfig
from shared.vio.states import corrected_state, placeholder_state
from shared.vio.window_rules import keyframe_due

log = logging.getLogger("sigmaslam.fast_path")


class FastPath:
    """Per-frame state from the back end's newest window (``cfg``: the VIO config, the ``backend`` section; ``cameras``:
    the rig's calibrations)."""

    def __init__(self, cfg: VioConfig, cameras) -> None:
        self.cfg = cfg
        self.budget_ms = cfg.fast_path_budget_ms
        self.tracker = FrameTracker(cfg, rig_cameras(cameras))
        self.waits_for_window = cfg.fast_path_waits_for_window
        self._expected_window_ns = -1  # the last frame the back end makes a keyframe of (its window is due)
        self._reset_pending = False
        self.dropped = 0
        self.seq = 0

    def window_stamp(self) -> int:
        """The stamp the window input must have reached before the next frame is handled (-1: do not wait)."""
        return self._expected_window_ns if self.waits_for_window else -1

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
        if keyframe_due(stamp, bool(frame.is_keyframe), last, self.cfg.max_keyframe_interval_s):
            self._expected_window_ns = stamp

    def state_of(self, frame: FeatureFrame) -> EstimatorState | None:
        """The frame's state in W' (a placeholder saying 'initialising' or, after a back-end restart, 'reset' while
        there is no window); None for a frame that cannot be tracked (dropped, counted, logged)."""
        stamp = int(frame.header.stamp_ns)
        self._note_keyframe(frame)
        try:
            st = self.tracker.track(stamp, frame.landmark_ids, frame.camera_index, frame.uv)
        except ValueError as exc:  # StaleFrame, ImuDataError, arrays that do not fit
            self.dropped += 1
            log.warning("feature frame %d dropped (%d so far): %s", stamp, self.dropped, exc)
            return None
        w = self.tracker.window  # its frame: 'W', or shared.map_folder.UNALIGNED_FRAME before a relocalisation
        header = Header(stamp_ns=stamp, seq=self.seq, frame_id=(w.header.frame_id or "W") if w is not None else "W")
        self.seq += 1
        if st is None:  # no window (yet, or since a back-end restart): say so (a lockstep player waits for an answer);
            # after a restart the first such state says 'reset' (consumers drop their history), as the back end's did
            status, self._reset_pending = ("reset" if self._reset_pending else "initialising"), False
            return placeholder_state(header, status)
        state = EstimatorState(header=header, T_WS=np.ascontiguousarray(st.T_WS, np.float64),
                               v_W=np.asarray(st.v_W, np.float64), gyro_bias=np.asarray(st.gyro_bias, np.float64),
                               acc_bias=np.asarray(st.acc_bias, np.float64), covariance=np.full((15, 15), np.nan),
                               status=st.status)
        T = np.asarray(self.tracker.window.T_corr, float)
        return state if np.allclose(T, np.eye(4)) else corrected_state(state, T)
