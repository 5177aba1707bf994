"""Configuration of the ROS 2 face (``sigmaslam ros2``) and of the live ROS 2 input (``sigmaslam ros2_input``)."""

from __future__ import annotations

import dataclasses
from typing import Literal

from shared.config import param

_IDENTITY = (1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0)


@dataclasses.dataclass(frozen=True)
class Ros2Topics:
    """ROS 2 topic names of the outputs; relative names are under ``ros2.namespace``, absolute ones ('/tf') as
    written."""

    odom: str = param("odom", "nav_msgs/Odometry: the causal pose of base_link in odom, per camera frame")
    tf: str = param("tf", "tf2_msgs/TFMessage: map -> odom (loop-closure correction) and odom -> base_link")
    tf_static: str = param("tf_static", "tf2_msgs/TFMessage: base_link -> each camera and the IMU")
    path: str = param("path", "nav_msgs/Path: the keyframes, loop-closed, in map")
    landmarks: str = param("landmarks", "sensor_msgs/PointCloud2: the window's landmarks, in odom")
    map_cloud: str = param("map_cloud", "sensor_msgs/PointCloud2: the submaps' surface points, in map")
    map_grid: str = param("map_grid", "nav_msgs/OccupancyGrid: the 2D grid of map/grid, in map")
    map_mesh: str = param("map_mesh", "visualization_msgs/Marker TRIANGLE_LIST: one per submap (id = submap id), in map")


@dataclasses.dataclass(frozen=True)
class Ros2InputTopics:
    """The robot's ROS 2 topics read by ``sigmaslam ros2_input`` (relative names under ``ros2.input.namespace``)."""

    cameras: tuple[str, ...] = param(("cam0/image_raw", "cam1/image_raw"), "image topics in rig order "
                                     "(sensor_msgs/Image mono8/bgr8/rgb8, or sensor_msgs/CompressedImage when the "
                                     "name ends in /compressed)")
    imu: str = param("imu0", "sensor_msgs/Imu topic")
    camera_info: tuple[str, ...] = param((), "sensor_msgs/CameraInfo topics in rig order, checked against the "
                                         "rig's image size ('' or none: the rig calibration alone)")


@dataclasses.dataclass(frozen=True)
class Ros2InputConfig:
    """A robot's camera and IMU topics as the pipeline's sensors (``sigmaslam ros2_input``)."""

    enabled: bool = param(False, "start sigmaslam ros2_input with the pipeline (sigmaslam up --ros2-input CONFIG)")
    namespace: str = param("", "ROS namespace of the robot's topics ('' = root)")
    topics: Ros2InputTopics = param(Ros2InputTopics(), "the robot's topics")
    sync_tolerance_ms: float = param(2.0, "images of one frame are paired by header stamp within this", "ms")
    max_pending_frames: int = param(8, "unpaired images kept per camera before the oldest is dropped")


@dataclasses.dataclass(frozen=True)
class Ros2Config:
    """sigmaslam as a ROS 2 participant on Zenoh (rmw_zenoh's wire format, no ROS installation): its outputs as
    ROS 2 topics (``sigmaslam ros2``) and a robot's sensors as input (``input``)."""

    enabled: bool = param(False, "start the ROS 2 face (sigmaslam ros2) with the pipeline")
    domain_id: int = param(0, "ROS_DOMAIN_ID of the ROS 2 network")
    namespace: str = param("", "ROS namespace of the face's node and relative topics ('' = root, e.g. '/robot0')")
    node_name: str = param("sigmaslam", "ROS node name shown by `ros2 node list`")
    connect: tuple[str, ...] = param((), "Zenoh endpoints of the ROS 2 network (rmw_zenoh's router, e.g. "
                                     "tcp/127.0.0.1:7447); () = the same as transport.connect")
    attachment: Literal["labelled", "plain"] = param("labelled", "rmw_zenoh attachment layout: 'labelled' (Jazzy "
                                                     "releases: each value after its name) or 'plain' (later ones)")
    topics: Ros2Topics = param(Ros2Topics(), "output topic names")
    map_frame: str = param("map", "frame id of the loop-closed world")
    odom_frame: str = param("odom", "frame id of the causal world (the estimator's W)")
    base_frame: str = param("base_link", "frame id of the robot's body")
    imu_frame: str = param("imu", "frame id of the IMU (the estimator's S); cameras are named as in the rig")
    T_BS: tuple[float, ...] = param(_IDENTITY, "pose of the IMU/body frame S in base_link, 4x4 row-major "
                                    "(identity: base_link is S)")
    cloud_period_s: float = param(1.0, "map_cloud at most this often", "s")
    mesh_period_s: float = param(2.0, "map_mesh markers (changed submaps) at most this often", "s")
    static_period_s: float = param(2.0, "tf_static is sent again this often (late joiners get it)", "s")
    max_cloud_points: int = param(200000, "map_cloud keeps every n-th point beyond this many")
    input: Ros2InputConfig = param(Ros2InputConfig(), "live ROS 2 sensor input")

    def __post_init__(self) -> None:
        if len(self.T_BS) != 16:
            raise ValueError(f"ros2.T_BS: 16 numbers (4x4 row-major), got {len(self.T_BS)}")
        if self.domain_id < 0 or self.domain_id > 232:
            raise ValueError(f"ros2.domain_id must be in 0..232, got {self.domain_id}")
        if min(self.cloud_period_s, self.mesh_period_s, self.static_period_s) <= 0:
            raise ValueError("ros2.cloud_period_s, mesh_period_s and static_period_s must be positive")
