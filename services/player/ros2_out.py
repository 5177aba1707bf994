"""The player as a stand-in ROS 2 robot (``sigmaslam player DATASET --as-ros2``): the dataset's frames and IMU samples
published as a robot's drivers publish them over rmw_zenoh (shared/ros2_wire.py), on the topics ``ros2.input`` names
(so that ``sigmaslam ros2_input`` with the same config reads them): per camera a sensor_msgs/Image (``mono8``, or
``--ros2-encoding bgr8``/``rgb8``) or, on a topic whose name ends in 'compressed', a CompressedImage (PNG lossless,
or JPEG with ``--ros2-encoding jpeg``), its CameraInfo on ``<camera topic's folder>/camera_info``, and a
sensor_msgs/Imu per sample. Stamps are the dataset's; the node is ``robot`` in ``ros2.input.namespace``.
"""

from __future__ import annotations

import logging
import posixpath

from shared import ros2_sensors as rs
from shared import ros2_wire as wire

log = logging.getLogger("sigmaslam.player")


class _Out:
    def __init__(self, fn) -> None:
        self.publish = fn


class RosRobot:
    """The ROS 2 publishers of a stand-in robot; :attr:`imu` and :attr:`frame` stand in for the player's own."""

    def __init__(self, cfg, cameras, encoding: str = "mono8") -> None:
        from transport.rmw_zenoh import RosParticipant, participant_config

        icfg = cfg.ros2.input
        self.ts, self.cameras, self.encoding = wire.type_store(), list(cameras or []), encoding
        self.ros = RosParticipant(participant_config(cfg.transport, cfg.ros2.connect), cfg.ros2.domain_id,
                                  icfg.namespace, "robot", cfg.ros2.attachment).open()
        self.cam_topics = list(icfg.topics.cameras)
        self.cam_types = [rs.image_type_of(t) for t in self.cam_topics]
        self.cam_pubs = [self.ros.publisher(t, typ) for t, typ in zip(self.cam_topics, self.cam_types)]
        self.info_pubs = [self.ros.publisher(posixpath.join(_folder(t), "camera_info"), rs.CAMERA_INFO_TYPE)
                          for t in self.cam_topics[:len(self.cameras)]]
        self.imu_pub = self.ros.publisher(icfg.topics.imu, rs.IMU_TYPE)
        self.imu, self.frame = _Out(self.put_imu), _Out(self.put_frame)

    def put_imu(self, sample) -> None:
        self.imu_pub.put(bytes(self.ts.serialize_cdr(rs.imu_msg(self.ts, sample, "imu"), rs.IMU_TYPE)))

    def put_frame(self, frame) -> None:
        for i, (img, name) in enumerate(zip(frame.images, frame.camera_names)):
            if i >= len(self.cam_pubs):
                break
            ns = int(frame.stamps_ns[i])
            if self.cam_types[i] == rs.COMPRESSED_TYPE:
                msg = rs.compressed_msg(self.ts, ns, name, img, "jpeg" if self.encoding == "jpeg" else "png")
            else:
                msg = rs.image_msg(self.ts, ns, name, img, self.encoding if self.encoding != "jpeg" else "mono8")
            self.cam_pubs[i].put(bytes(self.ts.serialize_cdr(msg, self.cam_types[i])))
            if i < len(self.info_pubs):
                info = rs.camera_info_msg(self.ts, ns, self.cameras[i])
                self.info_pubs[i].put(bytes(self.ts.serialize_cdr(info, rs.CAMERA_INFO_TYPE)))

    def close(self) -> None:
        self.ros.close()


def _folder(topic: str) -> str:
    """'cam0/image_raw' -> 'cam0'; 'cam0/image_raw/compressed' -> 'cam0'."""
    parts = topic.rstrip("/").split("/")
    if parts[-1] == "compressed":
        parts = parts[:-1]
    return "/".join(parts[:-1]) or "camera"
