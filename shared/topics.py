"""Every topic of sigmaslam in one place: relative key, message type, default queue policy.

A topic's Zenoh key expression is ``<namespace>/<key>`` (namespace from TransportConfig, e.g.
``sigmaslam/robot0``) so that several robots share one Zenoh network.
"""

from __future__ import annotations

import dataclasses

from shared.codec import Message
from shared import messages as m


@dataclasses.dataclass(frozen=True)
class Topic:
    key: str  # relative key expression, e.g. "sensors/imu"
    msg_type: type[Message]
    queue_policy: str = "latest"  # "latest": keep the newest N, drop the oldest; "all": never drop (IMU)
    queue_depth: int = 4  # N for "latest"; soft bound for "all" (beyond it drops are counted)
    doc: str = ""

    def key_expr(self, namespace: str) -> str:
        return f"{namespace.rstrip('/')}/{self.key}"


@dataclasses.dataclass(frozen=True)
class Question:
    """A question a process answers over Zenoh (a queryable at ``<namespace>/<key>``): a request message in, an
    answer message out, or an error reply with the reason as UTF-8 text."""

    key: str
    request: type[Message]
    answer: type[Message]
    doc: str = ""

    def key_expr(self, namespace: str) -> str:
        return f"{namespace.rstrip('/')}/{self.key}"


IMU = Topic("sensors/imu", m.ImuSample, "all", 4096, "raw IMU samples from the player or a driver")
FRAME = Topic("sensors/frame", m.MultiCameraFrame, "latest", 4, "synchronised multi-camera images")
FEATURES = Topic("frontend/frame", m.FeatureFrame, "all", 64, "tracked features per frame")
STATE = Topic("estimator/state", m.EstimatorState, "latest", 64, "causal pose per camera frame")
KEYFRAMES = Topic("estimator/keyframes", m.Keyframes, "latest", 8, "keyframe poses after each optimisation")
DEPTH_STEREO = Topic("depth/stereo", m.DepthFrame, "latest", 2, "stereo-network depth with sigma")
DEPTH_FUSED = Topic("depth/fused", m.DepthFrame, "latest", 2, "fused stereo+MVS depth with sigma")
SUBMAP = Topic("map/submap", m.SubmapMesh, "latest", 16, "submap mesh and pose")
STATS = Topic("stats/*", m.ServiceStats, "latest", 32, "per-service statistics; publish on stats/<service>")
HEARTBEAT = Topic("heartbeat/*", m.Heartbeat, "latest", 32, "per-service liveness; publish on heartbeat/<service>")
CONTROL = Topic("control", m.Control, "all", 64, "commands to services")
STREAM_END = Topic("sensors/end", m.StreamEnd, "all", 8, "end of a data source")
KEYFRAME_FEATURES = Topic("frontend/keyframe_features", m.KeyframeFeatures, "all", 64,
                          "ORB descriptors of each frontend keyframe (loop closure)")
TRAJECTORY_FINAL = Topic("estimator/trajectory_final", m.FinalTrajectory, "all", 4,
                         "non-causal trajectory after the final bundle adjustment (end of stream)")
MAP_FIELD = Topic("map/field", m.OccupancyField, "latest", 16,
                  "near-surface occupancy of a submap (L, w per voxel) for occupancy-to-point factors")
MAP_GRID = Topic("map/grid", m.OccupancyGrid2D, "latest", 2,
                 "2D occupancy grid of the combined map over a height band in W (navigation), at mapping.grid.rate_hz")
MAP_O2P_POINTS = Topic("map/o2p_points", m.SubmapPoints, "all", 64,
                       "lowest-sigma fused-depth points of a closed submap (map-to-map occupancy-to-point factors)")
LANDMARKS = Topic("estimator/landmarks", m.Landmarks, "latest", 4,
                  "well-constrained window landmarks after each keyframe optimisation (MVS prior, viewer)")
WINDOW = Topic("estimator/window", m.EstimatorWindow, "latest", 4,
               "newest keyframe state and window landmarks after each keyframe optimisation (the per-frame fast path)")

ALL: tuple[Topic, ...] = (IMU, FRAME, FEATURES, STATE, KEYFRAMES, DEPTH_STEREO, DEPTH_FUSED, SUBMAP,
                          STATS, HEARTBEAT, CONTROL, STREAM_END, KEYFRAME_FEATURES, TRAJECTORY_FINAL, MAP_FIELD,
                          MAP_GRID, MAP_O2P_POINTS, LANDMARKS, WINDOW)

MAP_QUERY = Question("map/query", m.OccupancyQuery, m.OccupancyAnswer,
                     "occupancy of the combined map at points, along segments, in boxes (W)")
QUESTIONS: tuple[Question, ...] = (MAP_QUERY,)


def per_service(topic: Topic, service: str) -> str:
    """Relative key of a per-service topic such as stats/<service>."""
    return topic.key.replace("*", service)
