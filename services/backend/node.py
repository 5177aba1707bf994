"""The back end as a transport-free process node: sensors/imu (keep-all) + frontend/frame -> estimator/window,
estimator/keyframes and estimator/landmarks after each keyframe's window optimisation; with loop closure,
frontend/keyframe_features and estimator/state (the published poses) in and, at the end of the stream,
estimator/trajectory_final out; with occupancy-to-point factors, map/field, map/o2p_points and depth/stereo in.

The back end handles only the frames its estimator makes keyframes of (``WindowedVioEstimator.wants_frame``): the
state of every frame is published by the fast path in the frontend's process (services/frontend/fast_path.py) from
the window this node publishes, so no frame waits for a window optimisation.

:class:`BackendNode` holds its stages, built by the composition root (services/backend/compose.py): the keyframe
window (services/backend/window/stage.py), the occupancy-to-point terms (services/backend/o2p/, ``o2p.enabled``) and
loop closure (services/backend/loop/stage.py, ``loop.enabled``); it hands each input to the stage it is for and
passes between the two optional stages what one gives the other. Run over Zenoh by ``sigmaslam backend`` or in one
process by :class:`shared.dataflow.InProcessRunner`.
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

from shared import topics
from shared.backlog import shed_backlog
from shared.dataflow import Emit, Input, ProcessNode
from shared.messages import EstimatorState, FeatureFrame, ImuSample, KeyframeFeatures, StreamEnd
from shared.process_description import ProcessDescription, Scheduling, Start

if TYPE_CHECKING:
    from services.backend.compose import BackendParts
    from services.backend.window.estimator import WindowedVioEstimator

log = logging.getLogger("sigmaslam.backend")


class BackendNode(ProcessNode):
    """The back end's process node over the stages of ``parts``; ``bc``: the backend config section."""

    name = "backend"
    stage = "optimise"
    inputs = (
        Input(topics.FEATURES, "on_features", role="trigger", shed="shed", note="tracks of each frame"),
        Input(topics.IMU, "on_imu", wait_until_trigger_stamp=True, note="pre-integration, up to the frame's time"),
        Input(topics.MAP_FIELD, "on_map_input", policy="all", depth=64, when="o2p.enabled",
              note="submap fields for the occupancy-to-point factors"),
        Input(topics.MAP_O2P_POINTS, "on_map_input", when="o2p.enabled", note="map-to-map points"),
        Input(topics.DEPTH_STEREO, "on_map_input", depth=8, when="o2p.enabled", note="frame-to-map points"),
        Input(topics.KEYFRAME_FEATURES, "on_keyframe_features", when="loop.enabled", note="loop detection"),
        Input(topics.STATE, "on_state", policy="all", depth=256, when="loop.enabled",
              note="the fast path's published poses: the frames of the final trajectory"),
        Input(topics.STREAM_END, "on_stream_end", role="idle", when="loop.enabled",
              note="the final bundle adjustment after the last frame"),
    )
    outputs = (topics.WINDOW, topics.KEYFRAMES, topics.LANDMARKS, topics.TRAJECTORY_FINAL)
    output_notes = {topics.WINDOW.key: "after each keyframe's optimisation",
                    topics.KEYFRAMES.key: "after each keyframe's optimisation",
                    topics.LANDMARKS.key: "after each keyframe's optimisation",
                    topics.TRAJECTORY_FINAL.key: "once, after sensors/end (loop.enabled)"}

    def __init__(self, bc, parts: BackendParts) -> None:
        self.bc, self.budget_ms, self.wait_s = bc, bc.budget_ms, bc.imu_wait_s
        self.window, self.o2p, self.loop_closure = parts.window, parts.o2p, parts.loop_closure
        used = ["on_features", "on_imu"]
        if self.o2p is not None:
            used.append("on_map_input")
        if self.loop_closure is not None:
            used += ["on_keyframe_features", "on_state", "on_stream_end"]
        self.use_inputs(used)
        self.skipped_frames = 0  # frames the estimator did not want (no keyframe): the fast path's alone
        self.skipped_keyframes = 0  # keyframes skipped to catch up (shed)

    @property
    def estimator(self) -> WindowedVioEstimator:
        return self.window.estimator

    def shed(self, pending) -> tuple[list, int]:
        """Live only (the transport runner calls it before each feature frame with what waits): skip what
        :func:`shed_backlog` says, counting the keyframes among them."""
        kept, skipped = shed_backlog(pending, self.bc.max_backlog_frames, max_keyframes=self.bc.max_backlog_keyframes)
        self.skipped_keyframes += sum(bool(f.is_keyframe) for f in pending) - sum(bool(f.is_keyframe) for f in kept)
        return kept, skipped

    def counters(self) -> dict:
        return {"keyframes_skipped": lambda: self.skipped_keyframes}  # shed as backlog: never in the window

    def on_imu(self, sample: ImuSample) -> None:
        self.window.add_imu(sample)

    def on_map_input(self, msg) -> None:
        self.o2p.add_message(msg, self.estimator)

    def on_keyframe_features(self, msg: KeyframeFeatures) -> None:
        self.loop_closure.add_keyframe_features(msg)

    def on_state(self, msg: EstimatorState) -> None:
        self.loop_closure.record_state(msg)

    def _exchange(self) -> None:
        """Between the optional stages: map-to-map terms of submaps closed since the last frame go to the pose
        graph; a verified revisit tells the occupancy terms which old landmarks the keyframe co-observes."""
        for term in self.o2p.pop_map_to_map():
            self.loop_closure.add_map_to_map(term)
        for stamp_ns, old_landmarks in self.loop_closure.take_revisits():
            self.o2p.note_loop(stamp_ns, old_landmarks)

    def on_features(self, frame: FeatureFrame) -> list[Emit]:
        if not self.window.wants(frame):
            if self.o2p is not None:
                self.o2p.note_frame(int(frame.header.stamp_ns), frame.landmark_ids)
            self.skipped_frames += 1
            return []
        loop = self.loop_closure
        if loop is not None:
            loop.before_frame()
            if self.o2p is not None:
                self._exchange()
        if self.o2p is not None:
            self.o2p.note_frame(int(frame.header.stamp_ns), frame.landmark_ids)
        msgs = self.window.process(frame)
        if loop is not None:
            msgs = loop.after_frame(msgs)
        out = []
        if msgs is not None:
            T_corr = loop.correction() if loop is not None else None
            out.append(Emit(topics.WINDOW, self.window.window_message(msgs[0], T_corr)))
            if msgs[1] is not None:
                out.append(Emit(topics.KEYFRAMES, msgs[1]))
        if (lms := self.window.take_landmarks()) is not None:
            out.append(Emit(topics.LANDMARKS, lms if loop is None else loop.correct_landmarks(lms)))
        return out

    def _final(self, ends: list[StreamEnd]) -> list[Emit]:
        final = self.loop_closure.poll_end(ends) if self.loop_closure is not None else None
        return [] if final is None else [Emit(topics.TRAJECTORY_FINAL, final)]

    def on_stream_end(self, msg: StreamEnd) -> list[Emit]:
        return self._final([msg])

    def tick(self) -> list[Emit]:
        """While idle: the final trajectory once the stream has ended and no frame came for a while."""
        return self._final([])

    def close(self) -> list[Emit]:
        if self.o2p is not None:  # how many dense factors the run used, and why others were not built
            log.info("o2p counts: %s", dict(sorted(self.o2p.counts.items())))
        if self.loop_closure is not None:
            self.loop_closure.close()
        return []


def make_node(cfg, cameras, restarted: bool = False) -> BackendNode:
    """The back-end node of the system config ``cfg`` for the rig ``cameras``, its stages built by the composition
    root (services/backend/compose.py)."""
    from services.backend.compose import build_backend

    return BackendNode(cfg.backend, build_backend(cfg, cameras, restarted))


def _build(cfg, start: Start) -> BackendNode:
    cameras = start.rig(cfg)
    log.info("backend: %d cameras", len(cameras))
    return make_node(cfg, cameras, restarted=start.restarts > 0)


def _warm_up(node: BackendNode) -> None:
    if node.o2p is not None:  # before the first heartbeat: a player waiting for the back end starts after this
        from shared.occupancy.query import warm_up

        t0 = time.monotonic()
        warm_up()
        log.info("backend: occupancy queries loaded in %.2f s", time.monotonic() - t0)


DESCRIPTION = ProcessDescription(
    name="backend", node=BackendNode, build=_build, warm_up=_warm_up, default_pipeline=True, in_process=True,
    # ahead of other work as the frontend is; SCHED_BATCH: its wake-ups do not preempt the frontend (at nice 10 it
    # skipped keyframes: docs/results/, stop 46; at nice -5 beside other programs' busy processes too, issue 60)
    scheduling=Scheduling(nice=-10, sched="batch"),
    help="visual-inertial window estimator: keyframes of frontend/frame + sensors/imu -> estimator/window, "
         "keyframes, landmarks (loop closure, o2p factors)")
