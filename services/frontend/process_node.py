"""The frontend process: the frontend node (images -> tracks, services/frontend/node.py) and the per-frame fast path
(tracks -> state, services/backend/odometry_node.py) in one process.

A frame's state leaves the process that tracked it: no second hop (serialise the tracks, send them, wake another
process and wait for a core) on the path from image to pose. The state is published first, then the tracks (the
back end's keyframe window reads them) and, at keyframes, their descriptors; the frontend takes its gyro bias from
the state it has just computed. The back end's window optimisation, marginalisation and loop closure stay in the
back end's process; the fast path picks up each new window when it comes (``estimator/window``).
"""

from __future__ import annotations

from shared.backlog import shed_backlog
from services.backend.odometry_node import OdometryNode
from services.frontend.node import FrontendNode
from shared import topics
from shared.dataflow import Emit, Input, ProcessNode
from shared.messages import EstimatorWindow, ImuSample, MultiCameraFrame


class FrontendProcessNode(ProcessNode):
    """Frontend and fast path of the system config ``cfg`` for the rig ``cameras``."""

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

    def __init__(self, cfg, cameras, first_landmark_id: int = 0) -> None:
        self.frontend = FrontendNode(cfg.frontend, cameras, first_landmark_id)
        self.fast_path = OdometryNode(cfg, cameras)
        # the parts time their stages through this node (the runner gives it the transport's timers)
        self.frontend.timer = self.fast_path.timer = self.timer
        self.names = self.frontend.names
        self.budget_ms = cfg.frontend.budget_ms + cfg.backend.fast_path_budget_ms
        self.wait_s = max(cfg.frontend.imu_wait_s, cfg.backend.imu_wait_s)
        self.max_backlog = cfg.frontend.max_backlog_frames

    def shed(self, pending) -> tuple[list, int]:
        return shed_backlog(pending, self.max_backlog, is_keyframe=lambda f: False)

    def wait_stamp(self, inp: Input, trigger_stamp_ns: int) -> int:
        return self.fast_path.wait_stamp(inp, trigger_stamp_ns) if inp.topic is topics.WINDOW else trigger_stamp_ns

    def on_imu(self, sample: ImuSample) -> None:
        self.frontend.on_imu(sample)
        self.fast_path.on_imu(sample)

    def on_window(self, msg: EstimatorWindow) -> None:
        self.frontend.on_window(msg)
        self.fast_path.on_window(msg)

    def on_frame(self, frame: MultiCameraFrame) -> list[Emit]:
        tracks = self.frontend.on_frame(frame)
        features = [e.msg for e in tracks if e.topic is topics.FEATURES]
        if not features:  # the frontend dropped the frame (counted and logged there)
            return tracks
        with self.timer("fast_path", self.fast_path.budget_ms):
            states = self.fast_path.on_features(features[0])
        for e in states:
            self.frontend.on_state(e.msg)
        return [*states, *tracks]

    def counters(self) -> dict:
        return self.frontend.counters()

    def after_publish(self) -> list[Emit]:
        return self.frontend.after_publish(behind=self.backlog > 0)
