"""The frontend as a transport-free process node: sensors/frame (+ sensors/imu gyro, estimator/state gyro bias)
-> frontend/frame (+ frontend/keyframe_features for loop closure).

:class:`FrontendNode` wraps :class:`services.frontend.tracker.MultiCameraTracker`: the gyro samples between two
frames give the rotation prior (bias-corrected with the estimator's latest gyro bias); a frame whose cameras do
not match the rig, or that goes back in time, is dropped, counted and logged. Run over Zenoh by
``sigmaslam frontend`` (services/frontend/service.py) or in one process by :class:`shared.dataflow.InProcessRunner`.
"""

from __future__ import annotations

import logging

import numpy as np

from services.frontend.gyro import GyroIntegrator
from services.frontend.tracker import FrontendInputError, MultiCameraTracker, TrackerOutput
from services.frontend.keyframe_features import keyframe_features_message
from shared import topics
from shared.dataflow import Emit, Input, ProcessNode, RejectedMessage
from shared.messages import EstimatorState, EstimatorWindow, FeatureFrame, Header, ImuSample, MultiCameraFrame

log = logging.getLogger("sigmaslam.frontend")


def feature_message(out: TrackerOutput, seq: int) -> FeatureFrame:
    n = len(out.landmark_ids)
    return FeatureFrame(header=Header(stamp_ns=out.stamp_ns, seq=seq, frame_id="rig"),
                        landmark_ids=np.asarray(out.landmark_ids, np.int64),
                        camera_index=np.asarray(out.camera_index, np.int16),
                        uv=np.ascontiguousarray(out.uv, np.float32).reshape(n, 2),
                        p_W_init=np.full((n, 3), np.nan), is_keyframe=bool(out.is_keyframe))


class FrontendNode(ProcessNode):
    """Per-frame logic of the frontend (images in, FeatureFrame out), without the transport."""

    name = "frontend"
    stage = "track"
    inputs = (
        Input(topics.FRAME, "on_frame", role="trigger", note="images to track"),
        Input(topics.IMU, "on_imu", wait_until_trigger_stamp=True, note="gyro rotation prior, up to the frame's time"),
        Input(topics.STATE, "on_state", policy="latest", depth=1, note="the newest gyro bias"),
        Input(topics.WINDOW, "on_window", policy="latest", depth=1,
              when="backend.refine_extrinsics or backend.estimate_time_offset",
              note="the refined camera extrinsics, the camera-IMU time offset"),
    )
    outputs = (topics.FEATURES, topics.KEYFRAME_FEATURES)
    output_notes = {topics.FEATURES.key: "every frame", topics.KEYFRAME_FEATURES.key: "each keyframe, before its frame"}

    def __init__(self, cfg, cameras, first_landmark_id: int = 0) -> None:
        self.cfg = cfg
        self.budget_ms, self.wait_s = cfg.budget_ms, cfg.imu_wait_s
        self.tracker = MultiCameraTracker(cfg, cameras, first_landmark_id)
        self.names = [c.name for c in cameras]
        self.gyro = GyroIntegrator()
        self.gyro_bias = np.zeros(3)
        self.estimator_status = ""  # the newest state's status: detection is deferred only while 'tracking'
        self.last_stamp: int | None = None
        self.dropped = 0
        self.seq = 0

    def on_imu(self, sample: ImuSample) -> None:
        self.gyro.add(int(sample.header.stamp_ns), sample.omega_S)

    def on_state(self, state: EstimatorState) -> None:
        self.gyro_bias = np.asarray(state.gyro_bias, float)
        self.estimator_status = str(state.status)

    def on_window(self, window: EstimatorWindow) -> None:
        try:
            if len(window.T_SC):  # the back end refines the extrinsics
                self.tracker.set_extrinsics(window.T_SC)
            if window.status not in ("initialising", "reset"):
                self.tracker.set_time_offset(float(window.time_offset_s))
        except FrontendInputError as exc:
            raise RejectedMessage(f"estimator/window refused: {exc}") from None

    def on_frame(self, frame: MultiCameraFrame) -> list[Emit]:
        msg = self.process(frame)
        if msg is None:
            return []
        out = []
        if msg.is_keyframe:  # descriptors first: the back end's loop closer wants them with the frame
            kff = keyframe_features_message(self.tracker, msg.header.stamp_ns, msg.header.seq)
            if kff is not None:
                out.append(Emit(topics.KEYFRAME_FEATURES, kff))
        out.append(Emit(topics.FEATURES, msg))
        return out

    def counters(self) -> dict:
        return {"detections_skipped": lambda: self.tracker.totals["detection_skipped"]}

    def after_publish(self, behind: bool = False) -> list[Emit]:
        """New features of a frame whose detection waited until its features were sent; none when ``behind`` (the
        next frame was waiting when this one was taken) and ``skip_detection_when_behind``."""
        if behind and self.cfg.skip_detection_when_behind:
            self.tracker.skip_deferred()
        if self.tracker.detection_pending:  # timed only when there is something to do (not after keyframes)
            with self.timer("detect_after"):
                self.tracker.finish_frame()
        return []

    def images_in_rig_order(self, frame: MultiCameraFrame):
        names = list(frame.camera_names)
        if names == self.names:
            return list(frame.images)
        try:
            return [frame.images[names.index(n)] for n in self.names]
        except ValueError:
            raise FrontendInputError(f"frame cameras {names} do not include the rig's {self.names}") from None

    def process(self, frame: MultiCameraFrame) -> FeatureFrame | None:
        stamp = int(frame.header.stamp_ns)
        try:
            images = self.images_in_rig_order(frame)
            R = None if self.last_stamp is None else self.gyro.rotation(self.last_stamp, stamp, self.gyro_bias)
            defer = self.cfg.defer_detection and self.estimator_status == "tracking"
            out = self.tracker.process(stamp, images, R, may_defer=defer)
        except FrontendInputError as exc:
            self.dropped += 1
            log.warning("frame %d dropped (%d so far): %s", stamp, self.dropped, exc)
            return None
        if self.last_stamp is not None:
            self.gyro.prune_before(self.last_stamp)
        self.last_stamp = stamp
        msg = feature_message(out, self.seq)
        self.seq += 1
        return msg
