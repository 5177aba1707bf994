"""``sigmaslam backend [CONFIG]``: sensors/imu (keep-all) + frontend/frame -> estimator/state (every frame),
estimator/keyframes (after each optimisation), estimator/landmarks (after each keyframe's optimisation).

Thin shell around :class:`services.backend.estimator.WindowedVioEstimator`. A feature frame waits up to
``backend.imu_wait_s`` for the IMU samples up to its time (they travel on their own topic); a frame the
estimator refuses (bad arrays, time going backwards, IMU gap) is dropped, counted and logged, never fatal.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import time
from collections import deque

import numpy as np

from services.backend.backlog import shed_backlog
from services.backend.estimator import BackendInputError, WindowedVioEstimator, camera_from_calib
from services.backend.imu_factors import ImuDataError
from shared.lookup_camera import LookupCamera
from services.backend.outputs import keyframes_message, landmarks_message, state_message
from services.backend.loop.backend_loop import LoopClosingBackend
from services.system_config import load_system_config
from shared.supervision import restart_count
from shared import topics
from shared.camera import CalibrationError
from shared.messages import DepthFrame, EstimatorState, FeatureFrame, Header, Keyframes, Landmarks, OccupancyField
from shared.rig import load_rig_config
from transport.node import Node
from transport.queues import Empty

log = logging.getLogger("sigmaslam.backend")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", nargs="?", help="YAML system config (default: built-in defaults)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")


class BackendShell:
    """Per-frame logic of the service without the transport."""

    def __init__(self, cfg, cameras) -> None:
        # undistortion by table lookup (the exact Newton inverse costs ~10 ms per frame at 300 observations)
        cams = [dataclasses.replace(c, camera=LookupCamera(c.camera)) for c in cameras]
        self.estimator = WindowedVioEstimator(cfg, [camera_from_calib(c) for c in cams])
        self.dropped = 0
        self.seq = 0
        self.newest_imu_ns = -1
        self.restarted = False  # set by main() after a supervisor restart: the first state says 'reset'
        self.o2p = None  # OccupancyTerms when occupancy-to-point factors are on (enable_o2p)
        self.landmarks: Landmarks | None = None  # of the last keyframe processed, until take_landmarks()

    def enable_o2p(self, cfg) -> None:
        """Occupancy-to-point factors (services/backend/o2p_terms.py) in every window optimisation."""
        from services.backend.o2p_terms import OccupancyTerms

        self.o2p = terms = OccupancyTerms(cfg)
        self.estimator.extra_factors = terms.window_factors  # none until the window has a metric scale (mono)

    def add_map_input(self, msg) -> None:
        """map/field (OccupancyField), depth/stereo (DepthFrame) or map/o2p_points (SubmapPoints) for o2p."""
        if self.o2p is None:
            return
        try:
            if isinstance(msg, DepthFrame):
                T_WS = None if np.allclose(msg.T_WC, np.eye(4)) else msg.T_WC @ np.linalg.inv(msg.T_SC)
                est = self.estimator
                self.o2p.add_depth(msg.header.stamp_ns, msg.depth, msg.sigma, msg.K, msg.T_SC, T_WS, est.stamps, est.values)
            elif isinstance(msg, OccupancyField):
                self.o2p.add_field(msg)
            else:
                self.o2p.add_submap_points(msg.submap_id, msg.points_M, msg.sigma)
        except ValueError as exc:
            self.o2p.counts["dropped_bad_input"] += 1
            log.warning("o2p input %s dropped: %s", type(msg).__name__, exc)

    def add_imu(self, sample) -> None:
        self.estimator.add_imu(int(sample.header.stamp_ns), sample.omega_S, sample.acc_S)
        self.newest_imu_ns = max(self.newest_imu_ns, int(sample.header.stamp_ns))

    def process(self, frame: FeatureFrame) -> tuple[EstimatorState, Keyframes | None] | None:
        msgs = self._process(frame)
        if msgs is not None and self.restarted:
            # a restarted back end lost its window: its first state says so (consumers treat 'reset' like
            # 'initialising': no pose to use), then it re-initialises from scratch
            self.restarted = False
            log.warning("back end restarted: state history lost, re-initialising (status 'reset' at %d)",
                        msgs[0].header.stamp_ns)
            msgs = (dataclasses.replace(msgs[0], status="reset"), msgs[1])
        return msgs

    def _process(self, frame: FeatureFrame) -> tuple[EstimatorState, Keyframes | None] | None:
        stamp = int(frame.header.stamp_ns)
        if self.o2p is not None:
            self.o2p.note_frame(stamp, frame.landmark_ids)
        try:
            res = self.estimator.process_frame(stamp, frame.landmark_ids, frame.camera_index, frame.uv,
                                               bool(frame.is_keyframe))
        except (BackendInputError, ImuDataError) as exc:
            self.dropped += 1
            log.warning("feature frame %d dropped (%d so far): %s", stamp, self.dropped, exc)
            return None
        if res is None:  # not initialised yet (needs IMU before the first frame): say so, for lockstep players
            msg = EstimatorState(header=Header(stamp_ns=stamp, seq=self.seq, frame_id="W"), T_WS=np.eye(4),
                                 v_W=np.zeros(3), gyro_bias=np.zeros(3), acc_bias=np.zeros(3),
                                 covariance=np.full((15, 15), np.nan), status="initialising")
            self.seq += 1
            return msg, None
        msgs = state_message(res, self.seq), keyframes_message(res, self.seq)
        self.landmarks = landmarks_message(res, self.seq)
        self.seq += 1
        return msgs

    def take_landmarks(self) -> Landmarks | None:
        """estimator/landmarks of the last frame processed if it was a keyframe (once)."""
        msg, self.landmarks = self.landmarks, None
        return msg


def main(args: argparse.Namespace) -> int:
    cfg = load_system_config(args.config, args.set)
    try:
        cameras = load_rig_config(cfg.rig)
    except (CalibrationError, FileNotFoundError) as exc:
        print(f"sigmaslam backend: {exc}", flush=True)
        return 2
    bc = cfg.backend
    shell = BackendShell(bc, cameras)
    shell.restarted = restart_count() > 0
    if cfg.o2p.enabled:  # before the loop closer, which hooks into the terms (anchors, correction)
        shell.enable_o2p(cfg.o2p)
    loop = LoopClosingBackend(shell, cfg.loop) if cfg.loop.enabled else None  # loop closure: services/backend/loop
    with Node("backend", cfg.transport) as node:
        imu = node.subscriber(topics.IMU)
        features = node.subscriber(topics.FEATURES)
        state_pub = node.publisher(topics.STATE)
        kf_pub = node.publisher(topics.KEYFRAMES)
        lm_pub = node.publisher(topics.LANDMARKS)
        kf_features = node.subscriber(topics.KEYFRAME_FEATURES)
        ends = node.subscriber(topics.STREAM_END)
        final_pub = node.publisher(topics.TRAJECTORY_FINAL)
        timer = node.timer("optimise", budget_ms=bc.budget_ms)
        map_inputs = []
        if shell.o2p is not None:  # occupancy-to-point inputs; drained before each frame, never waited for
            map_inputs = [node.subscriber(topics.MAP_FIELD, policy="all", depth=64),
                          node.subscriber(topics.MAP_O2P_POINTS), node.subscriber(topics.DEPTH_STEREO, depth=8)]
        log.info("backend: %d cameras", len(cameras))
        pending: deque = deque()  # frames taken from the queue, oldest first
        while not node.stopped:
            if not pending:
                try:
                    pending.append(features.get(timeout=0.1))
                except Empty:
                    for s in imu.drain():
                        shell.add_imu(s)
                    if loop is not None and (final := loop.poll_end(ends.drain())) is not None:
                        final_pub.publish(final)
                    continue
            pending.extend(features.drain())
            kept, skipped = shed_backlog(pending, bc.max_backlog_frames)
            if skipped:
                features.queue.count_shed(skipped)
                log.warning("backend: %d frames behind, skipped %d non-keyframes to catch up", len(pending), skipped)
            pending = deque(kept)
            frame = pending.popleft()
            stamp = int(frame.header.stamp_ns)
            deadline = time.monotonic() + bc.imu_wait_s
            for s in imu.drain():
                shell.add_imu(s)
            while shell.newest_imu_ns < stamp and time.monotonic() < deadline and not node.stopped:
                time.sleep(0.002)
                for s in imu.drain():
                    shell.add_imu(s)
            for sub in map_inputs:
                for m in sub.drain():
                    shell.add_map_input(m)
            if loop is not None:
                for kff in kf_features.drain():
                    loop.add_keyframe_features(kff)
            with timer:
                msgs = shell.process(frame) if loop is None else loop.process(frame)
            if msgs is not None:
                state_pub.publish(msgs[0])
                if msgs[1] is not None:
                    kf_pub.publish(msgs[1])
            if (lms := (shell if loop is None else loop).take_landmarks()) is not None:
                lm_pub.publish(lms)
    if shell.o2p is not None:  # how many dense factors the run used, and why others were not built
        log.info("o2p counts: %s", dict(sorted(shell.o2p.counts.items())))
    return 0
