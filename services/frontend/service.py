"""``sigmaslam frontend [CONFIG]``: sensors/frame (+ sensors/imu gyro, estimator/state gyro bias) ->
frontend/frame.

Thin shell around :class:`services.frontend.tracker.MultiCameraTracker`: the gyro samples between two
frames give the rotation prior (bias-corrected with the estimator's latest gyro bias); a frame whose
cameras do not match the rig, or that goes back in time, is dropped, counted and logged.
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np

from services.frontend.gyro import GyroIntegrator
from services.frontend.tracker import FrontendInputError, MultiCameraTracker, TrackerOutput
from services.frontend.keyframe_features import keyframe_features_message
from services.system_config import load_system_config
from shared.supervision import restart_count
from shared import topics
from shared.camera import CalibrationError
from shared.messages import FeatureFrame, Header, MultiCameraFrame
from shared.rig import load_rig_config
from transport.node import Node
from transport.queues import Empty

log = logging.getLogger("sigmaslam.frontend")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", nargs="?", help="YAML system config (default: built-in defaults)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")


def feature_message(out: TrackerOutput, seq: int) -> FeatureFrame:
    n = len(out.landmark_ids)
    return FeatureFrame(header=Header(stamp_ns=out.stamp_ns, seq=seq, frame_id="rig"),
                        landmark_ids=np.asarray(out.landmark_ids, np.int64),
                        camera_index=np.asarray(out.camera_index, np.int16),
                        uv=np.ascontiguousarray(out.uv, np.float32).reshape(n, 2),
                        p_W_init=np.full((n, 3), np.nan), is_keyframe=bool(out.is_keyframe))


class FrontendShell:
    """Per-frame logic of the service without the transport (images in, FeatureFrame out)."""

    def __init__(self, cfg, cameras, first_landmark_id: int = 0) -> None:
        self.cfg = cfg
        self.tracker = MultiCameraTracker(cfg, cameras, first_landmark_id)
        self.names = [c.name for c in cameras]
        self.gyro = GyroIntegrator()
        self.gyro_bias = np.zeros(3)
        self.last_stamp: int | None = None
        self.dropped = 0
        self.seq = 0

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
            out = self.tracker.process(stamp, images, R)
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


def main(args: argparse.Namespace) -> int:
    cfg = load_system_config(args.config, args.set)
    try:
        cameras = load_rig_config(cfg.rig)
    except (CalibrationError, FileNotFoundError) as exc:
        print(f"sigmaslam frontend: {exc}", flush=True)
        return 2
    # after a supervisor restart, landmark ids continue in a range of their own (2^40 ids per life)
    restarts = restart_count()
    shell = FrontendShell(cfg.frontend, cameras, first_landmark_id=restarts << 40)
    fc = cfg.frontend
    with Node("frontend", cfg.transport) as node:
        imu = node.subscriber(topics.IMU)
        frames = node.subscriber(topics.FRAME)
        states = node.subscriber(topics.STATE, policy="latest", depth=1)
        out = node.publisher(topics.FEATURES)
        kf_features = node.publisher(topics.KEYFRAME_FEATURES)  # loop closure (services/backend/loop)
        timer = node.timer("track", budget_ms=fc.budget_ms)
        log.info("frontend: %d cameras %s", len(cameras), shell.names)

        def drain_imu() -> int:
            latest = -1
            for s in imu.drain():
                shell.gyro.add(int(s.header.stamp_ns), s.omega_S)
                latest = max(latest, int(s.header.stamp_ns))
            return latest

        newest_imu = -1
        while not node.stopped:
            try:
                frame = frames.get(timeout=0.1)
            except Empty:
                newest_imu = max(newest_imu, drain_imu())
                continue
            stamp = int(frame.header.stamp_ns)
            deadline = time.monotonic() + fc.imu_wait_s
            newest_imu = max(newest_imu, drain_imu())
            while newest_imu < stamp and time.monotonic() < deadline and not node.stopped:
                time.sleep(0.002)
                newest_imu = max(newest_imu, drain_imu())
            for st in states.drain():
                shell.gyro_bias = np.asarray(st.gyro_bias, float)
            with timer:
                msg = shell.process(frame)
            if msg is not None:
                if msg.is_keyframe:  # descriptors first: the back end's loop closer wants them with the frame
                    kff = keyframe_features_message(shell.tracker, stamp, msg.header.seq)
                    if kff is not None:
                        kf_features.publish(kff)
                out.publish(msg)
    return 0
