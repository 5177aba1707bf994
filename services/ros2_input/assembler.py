"""A robot's ROS 2 camera and IMU samples -> the pipeline's sensor messages (no Zenoh here).

Each sample arrives as rmw_zenoh delivers it (topic, DDS type name, type hash, CDR payload). The assembler checks the
type against the one the topic is configured for (name and RIHS01 hash), decodes the CDR, takes the header stamp
as the time, turns images into grey, pairs the cameras of one frame by stamp (within ``sync_tolerance_ms``) and hands
back :class:`ImuSample` and :class:`MultiCameraFrame` messages, oldest first. What it cannot use is a counted drop
with a reason (:attr:`SensorAssembler.drops`) and a message saying which topic and why; nothing raises.
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict

import numpy as np

from shared import ros2_sensors as rs
from shared import ros2_wire as wire
from shared.messages import Header, ImuSample, MultiCameraFrame
from shared.ratelimit import RateLimitedLog

log = logging.getLogger("sigmaslam.ros2_input")

DROP_REASONS = ("wrong_type", "bad_cdr", "encoding", "image_size", "out_of_order", "bad_values", "no_imu", "unpaired",
                "camera_info")


class SensorAssembler:
    """See the module's docstring. ``cameras``: the rig (shared.camera.CameraCalib) in the order of
    ``camera_topics`` (fully qualified names); ``clock``: wall seconds, for the IMU stream's silence."""

    def __init__(self, cameras, camera_topics, imu_topic: str, info_topics=(), sync_tolerance_ms: float = 2.0,
                 max_pending: int = 8, imu_silence_s: float = 1.0, clock=time.monotonic) -> None:
        if len(cameras) != len(camera_topics):
            raise ValueError(f"{len(camera_topics)} camera topics for a rig of {len(cameras)} cameras")
        self.cameras, self.clock = list(cameras), clock
        self.types = {imu_topic: rs.IMU_TYPE, **{t: rs.image_type_of(t) for t in camera_topics},
                      **{t: rs.CAMERA_INFO_TYPE for t in info_topics if t}}
        self.cam_index = {t: i for i, t in enumerate(camera_topics)}
        self.info_index = {t: i for i, t in enumerate(info_topics) if t}
        self.imu_topic = imu_topic
        self.tol_ns, self.max_pending, self.imu_silence_s = int(sync_tolerance_ms * 1e6), max_pending, imu_silence_s
        self.pending: list[OrderedDict[int, np.ndarray]] = [OrderedDict() for _ in cameras]
        self.last_cam_ns = [-1] * len(cameras)
        self.last_imu_ns, self.last_imu_wall = -1, None
        self.last_frame_ns = -1
        self.seq_imu = self.seq_frame = 0
        self.drops = {k: 0 for k in DROP_REASONS}
        self.received = 0
        self._log = RateLimitedLog(log)

    def drop(self, reason: str, text: str) -> list:
        self.drops[reason] += 1
        self._log.warning("ros2_input: dropped (%s): %s", reason, text)
        return []

    def on_sample(self, topic: str, dds_type: str, type_hash: str, payload: bytes) -> list:
        """The messages ready to publish after this sample (may be empty)."""
        self.received += 1
        want = self.types.get(topic)
        if want is None:
            return []
        if dds_type != wire.dds_type_name(want) or type_hash != wire.type_hash(want):
            return self.drop("wrong_type", f"{topic}: {dds_type} {type_hash[:15]}..., expected {want} "
                                           f"{wire.type_hash(want)[:15]}... (a publisher of another type or ROS distro)")
        try:
            msg = wire.type_store().deserialize_cdr(payload, want)
        except Exception as exc:  # rosbags raises several types on truncated or garbled CDR
            return self.drop("bad_cdr", f"{topic}: {len(payload)} bytes do not decode as {want}: "
                                        f"{type(exc).__name__}: {exc}")
        if want == rs.IMU_TYPE:
            return self._imu(topic, msg)
        if want == rs.CAMERA_INFO_TYPE:
            return self._info(topic, msg)
        return self._image(topic, msg, want)

    def _imu(self, topic: str, msg) -> list:
        ns = rs.stamp_ns(msg)
        if ns <= self.last_imu_ns:
            return self.drop("out_of_order", f"{topic}: IMU stamp {ns} not after {self.last_imu_ns}")
        omega, acc = rs.imu_values(msg)
        if not (np.all(np.isfinite(omega)) and np.all(np.isfinite(acc))):
            return self.drop("bad_values", f"{topic}: non-finite IMU values at {ns}")
        self.last_imu_ns, self.last_imu_wall = ns, self.clock()
        self.seq_imu += 1
        return [ImuSample(header=Header(stamp_ns=ns, seq=self.seq_imu - 1, frame_id="S"), omega_S=omega, acc_S=acc)]

    def _info(self, topic: str, msg) -> list:
        cam = self.cameras[self.info_index[topic]].camera
        if (int(msg.width), int(msg.height)) != (cam.width, cam.height):
            return self.drop("camera_info", f"{topic}: {msg.width}x{msg.height}, the rig's camera is "
                                            f"{cam.width}x{cam.height} (wrong calibration for this camera?)")
        return []

    def _image(self, topic: str, msg, msgtype: str) -> list:
        i = self.cam_index[topic]
        ns = rs.stamp_ns(msg)
        if ns <= self.last_cam_ns[i]:
            return self.drop("out_of_order", f"{topic}: image stamp {ns} not after {self.last_cam_ns[i]}")
        try:
            grey = rs.image_to_grey(msg, msgtype)
        except rs.UnreadableImage as exc:
            return self.drop("encoding", f"{topic}: {exc}")
        cam = self.cameras[i].camera
        if grey.shape != (cam.height, cam.width):
            return self.drop("image_size", f"{topic}: {grey.shape[1]}x{grey.shape[0]}, the rig's "
                                           f"{self.cameras[i].name} is {cam.width}x{cam.height}")
        self.last_cam_ns[i] = ns
        self.pending[i][ns] = grey
        while len(self.pending[i]) > self.max_pending:
            self.pending[i].popitem(last=False)
            self.drop("unpaired", f"{topic}: more than {self.max_pending} images without a partner")
        return self._pair()

    def _pair(self) -> list:
        out = []
        for t0 in list(self.pending[0]):
            match = [min(p, key=lambda t: abs(t - t0), default=None) for p in self.pending[1:]]
            if any(t is None or abs(t - t0) > self.tol_ns for t in match):
                continue
            stamps = [t0, *match]
            images = [self.pending[0].pop(t0), *(p.pop(t) for p, t in zip(self.pending[1:], match))]
            for p, t in zip(self.pending, stamps):  # what is older than this frame will never be paired
                for old in [s for s in p if s < t]:
                    del p[old]
                    self.drop("unpaired", f"an image at {old} found no partner before {t}")
            out += self._frame(stamps, images)
        return out

    def _frame(self, stamps: list[int], images: list[np.ndarray]) -> list:
        t0 = stamps[0]
        wall = self.clock()
        if self.last_imu_wall is None or wall - self.last_imu_wall > self.imu_silence_s:
            return self.drop("no_imu", f"frame at {t0}: no IMU sample on {self.imu_topic} for "
                                       f"{'ever' if self.last_imu_wall is None else f'{wall - self.last_imu_wall:.1f} s'}"
                                       " (the estimator needs the IMU; is the IMU driver running?)")
        if t0 <= self.last_frame_ns:
            return self.drop("out_of_order", f"frame at {t0} not after {self.last_frame_ns}")
        self.last_frame_ns = t0
        self.seq_frame += 1
        return [MultiCameraFrame(header=Header(stamp_ns=t0, seq=self.seq_frame - 1, frame_id="rig"),
                                 images=tuple(images), camera_names=tuple(c.name for c in self.cameras),
                                 stamps_ns=np.asarray(stamps, np.int64))]
