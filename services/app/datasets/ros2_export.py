"""A sigmaslam recording as a ROS 2 bag (MCAP storage) with standard messages, for RViz, Foxglove and ros2 bag.

    sigmaslam convert RUN/recording.mcap OUT_BAG --to ros2
    sigmaslam run DATASET --out DIR --ros2-bag OUT_BAG      (records, then converts at the end)

Written with ``rosbags`` (no ROS needed); message definitions are stored in the bag, so ``ros2 bag info/play``
and Foxglove read it. The results are built by the ROS 2 face's own node (services/ros2/node.py) fed the recording
in order, so the bag and the live topics carry the same messages, frames (REP-105: ``map -> odom -> base_link``,
docs/ros2.md) and map -> odom correction; the depth images are the bag's own. Each message is logged at its header
stamp (the sensor's time, not the recording's wall clock), so the results play back in step with the input bag.

| topic | type | from | frame_id -> child |
|---|---|---|---|
| ``/sigmaslam/odom`` | nav_msgs/Odometry | estimator/state (causal, per frame) | ``odom`` -> ``base_link`` |
| ``/tf`` | tf2_msgs/TFMessage | the same poses, and the loop-closure correction | ``map`` -> ``odom`` -> ``base_link`` |
| ``/tf_static`` | tf2_msgs/TFMessage | the IMU, the depth camera in the body | ``base_link`` -> ``imu``, ``depth_camera`` |
| ``/sigmaslam/path`` | nav_msgs/Path | estimator/keyframes, estimator/trajectory_final (the last: non-causal) | ``map`` |
| ``/sigmaslam/landmarks`` | sensor_msgs/PointCloud2 | estimator/landmarks | ``odom`` |
| ``/sigmaslam/map_cloud`` | sensor_msgs/PointCloud2 | map/submap vertices, in the world | ``map`` |
| ``/sigmaslam/map_mesh`` | visualization_msgs/Marker | map/submap triangles (TRIANGLE_LIST, id = submap id) | ``map`` |
| ``/sigmaslam/map_grid`` | nav_msgs/OccupancyGrid | map/grid | ``map`` |
| ``/sigmaslam/depth`` | sensor_msgs/Image 32FC1 [m], NaN invalid | depth/fused | ``depth_camera`` |
| ``/sigmaslam/depth_sigma`` | sensor_msgs/Image 32FC1 [m] | depth/fused sigma | ``depth_camera`` |
| ``/sigmaslam/depth/camera_info`` | sensor_msgs/CameraInfo | depth/fused K (rectified pinhole) | ``depth_camera`` |
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from services.ros2.config import Ros2Config, Ros2Topics
from services.ros2.node import OUTPUT_TYPES, Ros2Node
from shared.ros2_wire import fq_topic

NAMESPACE = "/sigmaslam"
DEPTH_FRAME = "depth_camera"
DEPTH_TYPES = {"depth": "sensor_msgs/msg/Image", "sigma": "sensor_msgs/msg/Image", "info": "sensor_msgs/msg/CameraInfo",
               "depth_static": "tf2_msgs/msg/TFMessage"}
BAG_CONFIG = Ros2Config(namespace=NAMESPACE, topics=Ros2Topics(tf="/tf", tf_static="/tf_static"))
TOPICS = {**{k: fq_topic(NAMESPACE, getattr(BAG_CONFIG.topics, k)) for k in OUTPUT_TYPES},
          "depth": f"{NAMESPACE}/depth", "sigma": f"{NAMESPACE}/depth_sigma", "info": f"{NAMESPACE}/depth/camera_info",
          "depth_static": "/tf_static"}


def recording_to_ros2(recording: str | Path, out: str | Path, depth_every: int = 1) -> dict[str, int]:
    """Write the ROS 2 bag OUT (a folder, MCAP storage) from a sigmaslam recording; returns message counts per
    output (the keys of :data:`TOPICS`). ``depth_every``: keep every n-th depth frame (depth images are the bulk)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from services.recorder.mcap_reader import read_recording
    from shared import messages as m

    out = Path(out)
    if out.exists():
        raise FileExistsError(f"{out}: already exists (a ROS 2 bag is a new folder)")
    counts = {k: 0 for k in TOPICS}
    handlers = {m.EstimatorState: "on_state", m.Keyframes: "on_keyframes", m.FinalTrajectory: "on_final",
                m.Landmarks: "on_landmarks", m.SubmapMesh: "on_submap", m.OccupancyGrid2D: "on_grid"}
    sensor_s = [0.0]  # the node's clock: the sensor time of the newest message [s]
    n_depth = 0
    with Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns: dict = {}

        def put(key: str, cdr: bytes, stamp_ns: int) -> None:
            if key not in conns:  # the shared topic (/tf_static) gets one connection
                typ = {**OUTPUT_TYPES, **DEPTH_TYPES}[key]
                same = next((c for k, c in conns.items() if TOPICS[k] == TOPICS[key]), None)
                conns[key] = same or w.add_connection(TOPICS[key], typ, typestore=node.ros.ts)
            w.write(conns[key], int(stamp_ns), cdr)
            counts[key] += 1

        node = Ros2Node(BAG_CONFIG, [], put, clock=lambda: sensor_s[0])
        ros = node.ros
        for key_expr, _t, msg in read_recording(recording):
            stamp = int(msg.header.stamp_ns)
            if stamp > 0:
                sensor_s[0] = max(sensor_s[0], stamp * 1e-9)
            handler = handlers.get(type(msg))
            if handler is not None:
                getattr(node, handler)(msg)
                node.tick()
            elif isinstance(msg, m.DepthFrame) and msg.source in ("fused", "mvs") and "depth/fused" in key_expr:
                n_depth += 1
                if (n_depth - 1) % depth_every:
                    continue
                if counts["depth_static"] == 0:
                    put("depth_static", ros.cdr(ros.tf([ros.transform(stamp, BAG_CONFIG.base_frame, DEPTH_FRAME,
                                                                      ros.T_BS @ np.asarray(msg.T_SC))]),
                                                DEPTH_TYPES["depth_static"]), stamp)
                put("depth", ros.cdr(ros.image32(stamp, np.asarray(msg.depth), DEPTH_FRAME), DEPTH_TYPES["depth"]), stamp)
                put("sigma", ros.cdr(ros.image32(stamp, np.asarray(msg.sigma), DEPTH_FRAME), DEPTH_TYPES["sigma"]), stamp)
                put("info", ros.cdr(ros.camera_info(stamp, msg.K, np.asarray(msg.depth).shape, DEPTH_FRAME),
                                    DEPTH_TYPES["info"]), stamp)
        node.close()
    return counts
