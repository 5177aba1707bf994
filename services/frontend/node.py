"""The frontend process as one transport-free node: sensors/frame + sensors/imu + estimator/window ->
estimator/state (every frame), frontend/frame, frontend/keyframe_features.

:class:`FrontendNode` holds two collaborators: the multi-camera KLT tracker (services/frontend/tracker.py: images ->
tracks, gyro-aided) and the fast path (services/frontend/fast_path.py: tracks -> the frame's state against the back
end's newest window). A frame's state leaves the process that tracked it: no second hop on the path from image to
pose. The state is published first, then the tracks (the back end's keyframe window reads them) and, at keyframes,
their descriptors; the tracker takes its gyro bias from the state just computed. A frame whose cameras do not match
the rig, or that goes back in time, is dropped, counted and logged. The back end's window optimisation,
marginalisation and loop closure stay in the back end's process; the fast path picks up each new window when it comes
(``estimator/window``). Run over Zenoh by ``sigmaslam frontend`` or in one process by
:class:`shared.dataflow.InProcessRunner`.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

from services.frontend.frames import FrontendInputError, TrackerOutput
from services.frontend.gyro import GyroIntegrator
from services.frontend.keyframe_features import keyframe_features_message
from shared import topics
from shared.backlog import shed_backlog
from shared.dataflow import Emit, Input, ProcessNode, RejectedMessage
from shared.messages import EstimatorWindow, FeatureFrame, Header, ImuSample, MultiCameraFrame
from shared.process_description import ProcessDescription, Scheduling, Start

if TYPE_CHECKING:
    from services.frontend.fast_path import FastPath
    from services.frontend.tracker import MultiCameraTracker

log = logging.getLogger("sigmaslam.frontend")


def feature_message(out: TrackerOutput, seq: int) -> FeatureFrame:
    n = len(out.landmark_ids)
    return FeatureFrame(header=Header(stamp_ns=out.stamp_ns, seq=seq, frame_id="rig"),
                        landmark_ids=np.asarray(out.landmark_ids, np.int64),
                        camera_index=np.asarray(out.camera_index, np.int16),
                        uv=np.ascontiguousarray(out.uv, np.float32).reshape(n, 2),
                        p_W_init=np.full((n, 3), np.nan), is_keyframe=bool(out.is_keyframe))


class FrontendNode(ProcessNode):
    """Tracking and the fast path of one rig (``cfg``: the frontend config section)."""

    name = "frontend"
    stage = "track"  # a frame's whole path to its state: tracking, then the fast path (timed alone as 'fast_path')
    inputs = (
        Input(topics.FRAME, "on_frame", role="trigger", shed="shed",
              note="images to track (the oldest skipped beyond frontend.max_backlog_frames)"),
        Input(topics.IMU, "on_imu", wait_until_trigger_stamp=True,
              note="gyro rotation prior; pre-integration from the keyframe"),
        Input(topics.WINDOW, "on_window", policy="latest", depth=2, wait_until_trigger_stamp=True,
              note="the back end's newest keyframe and landmarks (waited for only in lockstep runs), refined "
                   "extrinsics, time offset"),
    )
    outputs = (topics.STATE, topics.KEYFRAME_FEATURES, topics.FEATURES)
    output_notes = {topics.STATE.key: "every frame, as soon as it is tracked",
                    topics.KEYFRAME_FEATURES.key: "each keyframe, before its frame",
                    topics.FEATURES.key: "every frame, after its state"}

    def __init__(self, cfg, tracker: MultiCameraTracker, fast_path: FastPath) -> None:
        self.cfg, self.tracker, self.fast_path = cfg, tracker, fast_path
        self.names = [c.name for c in tracker.cameras]
        self.budget_ms = cfg.budget_ms + fast_path.budget_ms
        self.wait_s = max(cfg.imu_wait_s, fast_path.cfg.imu_wait_s)
        self.gyro = GyroIntegrator()
        self.gyro_bias = np.zeros(3)
        self.estimator_status = ""  # the newest state's status: detection is deferred only while 'tracking'
        self.last_stamp: int | None = None
        self.dropped = 0
        self.seq = 0

    def shed(self, pending) -> tuple[list, int]:
        return shed_backlog(pending, self.cfg.max_backlog_frames, is_keyframe=lambda f: False)

    def wait_stamp(self, inp: Input, trigger_stamp_ns: int) -> int:
        return self.fast_path.window_stamp() if inp.topic is topics.WINDOW else trigger_stamp_ns

    def on_imu(self, sample: ImuSample) -> None:
        self.gyro.add(int(sample.header.stamp_ns), sample.omega_S)
        self.fast_path.on_imu(sample)

    def on_window(self, window: EstimatorWindow) -> None:
        try:
            if len(window.T_SC):  # the back end refines the extrinsics
                self.tracker.set_extrinsics(window.T_SC)
            if window.status not in ("initialising", "reset"):
                self.tracker.set_time_offset(float(window.time_offset_s))
        except FrontendInputError as exc:
            raise RejectedMessage(f"estimator/window refused: {exc}") from None
        self.fast_path.on_window(window)

    def on_frame(self, frame: MultiCameraFrame) -> list[Emit]:
        msg = self.track(frame)
        if msg is None:
            return []
        # a keyframe whose new features wait (frontend.keyframe_work_after_state): its tracks go out after_publish
        tracks = [] if self.tracker.keyframe_pending else self._tracks(msg)
        with self.timer("fast_path", self.fast_path.budget_ms):
            state = self.fast_path.state_of(msg)
        if state is None:
            return tracks + self.finish_keyframe()
        self.gyro_bias = np.asarray(state.gyro_bias, float)
        self.estimator_status = str(state.status)
        return [Emit(topics.STATE, state), *tracks]

    def _tracks(self, msg: FeatureFrame) -> list[Emit]:
        """A frame's tracks; at a keyframe its descriptors first (the back end's loop closer wants them with it)."""
        out = []
        if msg.is_keyframe:
            kff = keyframe_features_message(self.tracker, msg.header.stamp_ns, msg.header.seq)
            if kff is not None:
                out.append(Emit(topics.KEYFRAME_FEATURES, kff))
        return out + [Emit(topics.FEATURES, msg)]

    def finish_keyframe(self) -> list[Emit]:
        """The tracks of a keyframe whose work waited until its state was sent (none when nothing waited)."""
        if not self.tracker.keyframe_pending:
            return []
        with self.timer("keyframe_after"):
            out = self.tracker.finish_keyframe()
        return self._tracks(feature_message(out, self.seq - 1))  # the keyframe is the last frame tracked

    def counters(self) -> dict:
        return {"detections_skipped": lambda: self.tracker.totals["detection_skipped"]}

    def after_publish(self) -> list[Emit]:
        """The tracks of a keyframe whose work waited until its state was sent; new features of a frame whose
        detection waited until its features were sent (none when the next frame was waiting when this one was
        taken and ``skip_detection_when_behind``)."""
        if self.tracker.keyframe_pending:
            return self.finish_keyframe()
        if self.backlog > 0 and self.cfg.skip_detection_when_behind:
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

    def track(self, frame: MultiCameraFrame) -> FeatureFrame | None:
        """The frame's tracks (None: dropped, counted and logged)."""
        stamp = int(frame.header.stamp_ns)
        try:
            images = self.images_in_rig_order(frame)
            R = None if self.last_stamp is None else self.gyro.rotation(self.last_stamp, stamp, self.gyro_bias)
            tracking = self.estimator_status == "tracking"
            out = self.tracker.process(stamp, images, R, may_defer=self.cfg.defer_detection and tracking,
                                       may_defer_keyframe=self.cfg.keyframe_work_after_state and tracking)
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


def make_node(cfg, cameras, first_landmark_id: int = 0) -> FrontendNode:
    """The frontend node of the system config ``cfg`` for the rig ``cameras`` (``first_landmark_id``: where its
    landmark ids start; a restarted frontend starts a range of its own)."""
    from services.frontend.fast_path import FastPath
    from services.frontend.tracker import MultiCameraTracker

    return FrontendNode(cfg.frontend, MultiCameraTracker(cfg.frontend, cameras, first_landmark_id),
                        FastPath(cfg.backend, cameras))


def _build(cfg, start: Start) -> FrontendNode:
    # after a supervisor restart, landmark ids continue in a range of their own (2^40 ids per life)
    node = make_node(cfg, start.rig(cfg), first_landmark_id=start.restarts << 40)
    log.info("frontend: %d cameras %s", len(node.names), node.names)
    return node


def _warm_up(node: FrontendNode) -> None:
    """The frontend's own process only (never the in-process runner's, whose other nodes share OpenCV): its OpenCV
    threads (frontend.opencv_threads)."""
    if node.cfg.opencv_threads > 0:
        import cv2

        cv2.setNumThreads(node.cfg.opencv_threads)


DESCRIPTION = ProcessDescription(
    name="frontend", node=FrontendNode, build=_build, warm_up=_warm_up, default_pipeline=True, in_process=True,
    # the path to a pose: real-time where allowed, else ahead of other work by its nice (services/app/scheduling.py)
    scheduling=Scheduling(nice=-10, sched="fifo"),
    help="feature tracker and per-frame fast path: sensors/frame + sensors/imu + estimator/window -> "
         "estimator/state, frontend/frame")
