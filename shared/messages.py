"""Message types exchanged between sigmaslam processes.

Each is a frozen, keyword-only dataclass with a :class:`~shared.codec.Header`; array fields document
shape and dtype (names such as ``"N"`` are shared within one message and checked on construction).
Poses are 4x4 float64 homogeneous matrices ``T_AB`` (maps points from B to A). Times are int64 ns.
Wire format: :mod:`shared.codec`. Type ids are stable: never reuse a retired id.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from shared.codec import Header, Message, array_field, register, scalar_field
from shared.occupancy.uncertain_pixels import surface_depth

__all__ = [
    "Header", "ImuSample", "MultiCameraFrame", "FeatureFrame", "EstimatorState", "Keyframes",
    "DepthFrame", "SubmapMesh", "ServiceStats", "Heartbeat", "Control", "StreamEnd",
    "KeyframeFeatures", "FinalTrajectory", "OccupancyField", "OccupancyGrid2D", "OccupancyQuery", "OccupancyAnswer", "SubmapPoints", "Landmarks", "EstimatorWindow",
]


@register(1)
@dataclasses.dataclass(frozen=True, kw_only=True)
class ImuSample(Message):
    """One IMU reading in the IMU frame S (header.frame_id = 'S')."""

    omega_S: object = array_field("angular rate [rad/s]", "float64", (3,))
    acc_S: object = array_field("specific force (accelerometer reading) [m/s^2]", "float64", (3,))


@register(2)
@dataclasses.dataclass(frozen=True, kw_only=True)
class MultiCameraFrame(Message):
    """Synchronised images of all cameras of the rig; header.stamp_ns is the frame time."""

    images: tuple[object, ...] = array_field("one grayscale image per camera, (H_i, W_i) uint8", "uint8", ("H", "W"))
    camera_names: tuple[str, ...] = scalar_field("camera names, e.g. ('cam0', 'cam1'), same order as images")
    stamps_ns: object = array_field("exposure time of each camera [ns]", "int64", ("C",))


@register(3)
@dataclasses.dataclass(frozen=True, kw_only=True)
class FeatureFrame(Message):
    """Frontend output for one multi-camera frame: tracked landmark observations."""

    landmark_ids: object = array_field("landmark id of each observation", "int64", ("M",))
    camera_index: object = array_field("index of the observing camera", "int16", ("M",))
    uv: object = array_field("pixel coordinates (distorted image) [px]", "float32", ("M", 2))
    p_W_init: object = array_field("frontend's initial landmark position guess in W [m] (NaN if none)", "float64", ("M", 3))
    is_keyframe: bool = scalar_field("frontend selected this frame as a keyframe")


@register(4)
@dataclasses.dataclass(frozen=True, kw_only=True)
class EstimatorState(Message):
    """Causal estimate for one camera frame (header.frame_id = 'W')."""

    T_WS: object = array_field("body (IMU) pose in world", "float64", (4, 4))
    v_W: object = array_field("body velocity in world [m/s]", "float64", (3,))
    gyro_bias: object = array_field("gyroscope bias [rad/s]", "float64", (3,))
    acc_bias: object = array_field("accelerometer bias [m/s^2]", "float64", (3,))
    covariance: object = array_field(
        "marginal covariance, order [rot_S(3) rad, p_W(3) m, v_W(3) m/s, gyro_bias(3), acc_bias(3)]", "float64", (15, 15))
    status: str = scalar_field("'initialising', 'tracking', 'imu_only', 'lost' or 'reset'", default="tracking")


@register(5)
@dataclasses.dataclass(frozen=True, kw_only=True)
class Keyframes(Message):
    """Poses of recent (or all updated) keyframes after an optimisation."""

    ids: object = array_field("keyframe ids", "int64", ("K",))
    stamps_ns: object = array_field("keyframe times [ns]", "int64", ("K",))
    T_WS: object = array_field("keyframe body poses in world", "float64", ("K", 4, 4))


@register(6)
@dataclasses.dataclass(frozen=True, kw_only=True)
class DepthFrame(Message):
    """Depth with per-pixel standard deviation for one camera (header.frame_id = camera name)."""

    depth: object = array_field("depth along the optical axis [m]; NaN where invalid", "float32", ("H", "W"))
    sigma: object = array_field("depth standard deviation [m]; NaN where invalid", "float32", ("H", "W"))
    K: object = array_field("pinhole intrinsics of the (undistorted) depth image [px]", "float64", (3, 3))
    T_WC: object = array_field("camera pose in world used for integration (identity if unknown)", "float64", (4, 4))
    T_SC: object = array_field("pose of the (rectified) depth camera in the body frame S", "float64", (4, 4),
                               default_factory=lambda: np.eye(4))
    source: str = scalar_field("'stereo', 'mvs', 'fused' or 'gt'")
    surface_max_relative_sigma: float = scalar_field(
        "pixels whose sigma exceeds this fraction of their depth are too uncertain to place a surface: a map takes "
        "only the free space well in front of them (depth.max_relative_sigma; learned sigma only); 0: every pixel "
        "places its surface", default=0.0)

    def surface_depth(self) -> np.ndarray:
        """The depth with NaN where it places no surface: the depth points a user of surfaces wants."""
        return surface_depth(self.depth, self.sigma, self.surface_max_relative_sigma)


@register(7)
@dataclasses.dataclass(frozen=True, kw_only=True)
class SubmapMesh(Message):
    """Triangle mesh of one submap in its own frame M_j, with the submap's current pose."""

    submap_id: int = scalar_field("submap id")
    T_WM: object = array_field("submap pose in world", "float64", (4, 4))
    vertices_M: object = array_field("vertex positions in the submap frame [m]", "float32", ("V", 3))
    faces: object = array_field("vertex indices of each triangle", "int32", ("F", 3))
    vertex_colors: object = array_field("RGB per vertex (empty: no colour)", "uint8", ("V_c", 3))


@register(8)
@dataclasses.dataclass(frozen=True, kw_only=True)
class ServiceStats(Message):
    """Periodic statistics of one service: stage timings against budgets, queue drops, other counts."""

    service: str = scalar_field("service name")
    uptime_s: float = scalar_field("seconds since the service started [s]")
    rss_mb: float = scalar_field("resident memory [MiB]")
    stage_names: tuple[str, ...] = scalar_field("timed stages, order of the stage_* arrays")
    stage_count: object = array_field("items processed since start", "int64", ("S",))
    stage_rate_hz: object = array_field("items per second over the last window [Hz]", "float64", ("S",))
    stage_p50_ms: object = array_field("median compute time over the last window [ms]", "float64", ("S",))
    stage_p99_ms: object = array_field("99th percentile compute time over the last window [ms]", "float64", ("S",))
    stage_budget_ms: object = array_field("configured budget, NaN if none [ms]", "float64", ("S",))
    stage_overruns: object = array_field("items over budget since start", "int64", ("S",))
    queue_names: tuple[str, ...] = scalar_field("subscription queues, order of the queue_* arrays")
    queue_received: object = array_field("messages received since start", "int64", ("Q",))
    queue_dropped: object = array_field("messages dropped (queue full or undecodable) since start", "int64", ("Q",))
    queue_depth: object = array_field("messages waiting now", "int64", ("Q",))
    counter_names: tuple[str, ...] = scalar_field("counts the service keeps besides its queues (pixels, points, "
                                                  "frames of a kind), order of counter_values", default=())
    counter_values: object = array_field("each count since start", "int64", ("K",),
                                         default_factory=lambda: np.zeros(0, np.int64))


@register(9)
@dataclasses.dataclass(frozen=True, kw_only=True)
class Heartbeat(Message):
    """Liveness of one service, published at a fixed rate."""

    service: str = scalar_field("service name")
    pid: int = scalar_field("OS process id")
    state: str = scalar_field("'starting', 'running', 'stopping'")


@register(10)
@dataclasses.dataclass(frozen=True, kw_only=True)
class Control(Message):
    """A command to a service, e.g. to the player: 'pause', 'resume', 'stop'."""

    target: str = scalar_field("service the command is for ('*' for all)")
    command: str = scalar_field("command name")


@register(11)
@dataclasses.dataclass(frozen=True, kw_only=True)
class StreamEnd(Message):
    """A source has no more data (e.g. the player reached the end of the dataset)."""

    source: str = scalar_field("name of the source that ended")
    frames_sent: int = scalar_field("frames published by the source")


# --- occupancy mapping (type ids 50-59) ---


@register(50)
@dataclasses.dataclass(frozen=True, kw_only=True)
class OccupancyField(Message):
    """Near-surface occupancy of one submap (its voxel blocks that hold a surface), in the submap frame M_j
    (header.frame_id = 'M<j>'), for occupancy-to-point factors (eq. 6-7). Voxel (i, j, k) of block b has its
    centre at ``((block_ijk[b] * B + (i, j, k)) + 0.5) * voxel_size_m``; rebuild the queries with
    ``shared.occupancy.message.field_of_message``."""

    submap_id: int = scalar_field("submap id")
    T_WM: object = array_field("submap pose in world", "float64", (4, 4))
    voxel_size_m: float = scalar_field("voxel edge length [m]")
    l_min: float = scalar_field("log-odds of free space of the inverse sensor model (eq. 3, 7)")
    block_ijk: object = array_field("integer block coordinates, sorted by packed key", "int32", ("N", 3))
    log_odds: object = array_field("mean log-odds L per voxel (eq. 4), [block, x, y, z]", "float32", ("N", "B", "B", "B"))
    counts: object = array_field("observation count w per voxel (0 = unknown)", "uint16", ("N", "B", "B", "B"))


@register(51)
@dataclasses.dataclass(frozen=True, kw_only=True)
class OccupancyGrid2D(Message):
    """A 2D occupancy grid of the combined map over a height band of the gravity-aligned world frame W
    (header.frame_id = 'W', header.stamp_ns = time of the newest state the map was built with). Cell (row r, col c)
    covers ``x in origin_xy_m[0] + [c, c + 1) * resolution_m``, ``y in origin_xy_m[1] + [r, r + 1) * resolution_m``
    (row 0 at the lowest y, as in a ROS nav_msgs/OccupancyGrid); a cell is occupied when any voxel of the band in it
    is occupied, free when the band is observed free, else unknown. Values follow nav_msgs/OccupancyGrid: 0 free ..
    100 occupied, 255 unknown (-1 read as int8)."""

    resolution_m: float = scalar_field("cell edge length [m]")
    origin_xy_m: object = array_field("x, y in W of the corner of cell (0, 0) (its lowest x and y) [m]", "float64", (2,))
    z_band_m: object = array_field("height band [z_min, z_max] in W the grid summarises [m]", "float64", (2,))
    cells: object = array_field("occupancy per cell, [row (y), col (x)]: 0 free .. 100 occupied, 255 unknown",
                                "uint8", ("H", "W"))

    @property
    def width(self) -> int:
        """Cells along x (columns)."""
        return int(self.cells.shape[1])

    @property
    def height(self) -> int:
        """Cells along y (rows)."""
        return int(self.cells.shape[0])


@register(52)
@dataclasses.dataclass(frozen=True, kw_only=True)
class OccupancyQuery(Message):
    """A question to the combined map (``map/query``), everything in W (header.frame_id = 'W'). ``kind``
    'points': the state of each row of ``a_W``; 'segments': capsules from ``a_W`` to ``b_W`` with ``radius_m`` (one
    per segment, or one for all); 'boxes': axis-aligned boxes with corners ``a_W`` (lowest) and ``b_W`` (highest)."""

    kind: str = scalar_field("'points', 'segments' or 'boxes'")
    a_W: object = array_field("points, segment starts or box lower corners [m]", "float64", ("N", 3))
    b_W: object = array_field("segment ends or box upper corners (none for points) [m]", "float64", ("M", 3),
                              default_factory=lambda: np.zeros((0, 3)))
    radius_m: object = array_field("segment radius, one per segment or one for all (none: 0) [m]", "float64", ("R",),
                                   default_factory=lambda: np.zeros(0))


@register(53)
@dataclasses.dataclass(frozen=True, kw_only=True)
class OccupancyAnswer(Message):
    """The combined map's answer to an :class:`OccupancyQuery` (header.frame_id = 'W', header.stamp_ns = the newest
    depth frame the map holds). Only the arrays of the query's kind are filled, the others are empty. States:
    0 unknown, 1 free, 2 occupied."""

    kind: str = scalar_field("the query's kind")
    state: object = array_field("points: state of each point", "int8", ("N",))
    log_odds: object = array_field("points: combined log-odds (largest observed L; NaN unobserved)", "float32", ("N",))
    submaps: object = array_field("points: how many submaps observed the point", "int16", ("N",))
    hit: object = array_field("segments: an occupied point lies within the radius", "bool", ("K",))
    hit_distance_m: object = array_field("segments: distance along the segment of the first one (NaN: none) [m]",
                                         "float64", ("K",))
    hit_point_W: object = array_field("segments: that occupied point (NaN: none) [m]", "float64", ("K", 3))
    free: object = array_field("segments: every point of the capsule free", "bool", ("K",))
    any_occupied: object = array_field("boxes: an occupied point inside", "bool", ("B",))
    occupied_fraction: object = array_field("boxes: fraction of the box occupied", "float64", ("B",))
    unknown_fraction: object = array_field("segments and boxes: fraction unknown", "float64", ("U",))


# --- loop closure and the non-causal trajectory (type ids 70-79) ---


@register(70)
@dataclasses.dataclass(frozen=True, kw_only=True)
class KeyframeFeatures(Message):
    """Features of one frontend keyframe with their ORB descriptors (for loop closure); header.stamp_ns is the
    keyframe's frame time."""

    keyframe_id: int = scalar_field("frontend keyframe counter")
    landmark_ids: object = array_field("landmark id of each feature", "int64", ("K",))
    camera_index: object = array_field("index of the observing camera", "int16", ("K",))
    uv: object = array_field("pixel coordinates (distorted image) [px]", "float32", ("K", 2))
    descriptors: object = array_field("ORB descriptor of each feature (256 bits)", "uint8", ("K", 32))


@register(71)
@dataclasses.dataclass(frozen=True, kw_only=True)
class FinalTrajectory(Message):
    """Non-causal trajectory at the end of a stream (final bundle adjustment over all keyframes, loops), one
    pose per frame the estimator published; with the run's loop-closure counts."""

    stamps_ns: object = array_field("frame times [ns]", "int64", ("N",))
    T_WS: object = array_field("body poses in world", "float64", ("N", 4, 4))
    keyframes: int = scalar_field("keyframes in the final bundle adjustment")
    loops_proposed: int = scalar_field("place-recognition candidates verified by PnP")
    loops_verified: int = scalar_field("candidates PnP accepted")
    loops_accepted: int = scalar_field("loop factors added to the pose graph")
    relocalisations: int = scalar_field("relocalisations after a loss of tracking")


# --- occupancy-to-point factors (type ids 90-99) ---


@register(90)
@dataclasses.dataclass(frozen=True, kw_only=True)
class SubmapPoints(Message):
    """Lowest-sigma fused-depth points integrated into one submap, in its frame M_j (header.frame_id = 'M<j>',
    header.stamp_ns = the submap's creation time), for its map-to-map occupancy-to-point factor (eq. 6-7)."""

    submap_id: int = scalar_field("submap id")
    points_M: object = array_field("points in the submap frame [m]", "float32", ("N", 3))
    sigma: object = array_field("depth standard deviation of each point [m]", "float32", ("N",))


# --- estimator landmarks (type ids 100-109) ---


@register(100)
@dataclasses.dataclass(frozen=True, kw_only=True)
class Landmarks(Message):
    """Well-constrained landmarks of the estimator's window after a keyframe's optimisation (triangulated,
    finite, >= 2 window observations), in W (header.frame_id = 'W', header.stamp_ns = that keyframe's time).
    Sparse depth prior of the MVS network (sec. IV-D) and the viewer's landmark layer."""

    ids: object = array_field("landmark ids (the frontend's)", "int64", ("N",))
    p_W: object = array_field("landmark positions in world [m]", "float64", ("N", 3))
    num_observations: object = array_field("observations of the landmark in the window", "int32", ("N",))
    last_seen_ns: object = array_field("time of the newest window keyframe observing the landmark [ns]", "int64", ("N",))


@register(101)
@dataclasses.dataclass(frozen=True, kw_only=True)
class EstimatorWindow(Message):
    """What the per-frame fast path (services/frontend/odometry.py) needs of the back end's window after a keyframe's
    optimisation: the newest keyframe's state and the window's triangulated landmarks, both in the estimator's own
    frame W (header.frame_id = 'W', header.stamp_ns = that keyframe's time), and the loop closer's correction
    T_W'W into the frame states are published in (identity without loop closure)."""

    T_WS: object = array_field("newest keyframe's body pose in W", "float64", (4, 4))
    v_W: object = array_field("its velocity in W [m/s]", "float64", (3,))
    gyro_bias: object = array_field("its gyroscope bias [rad/s]", "float64", (3,))
    acc_bias: object = array_field("its accelerometer bias [m/s^2]", "float64", (3,))
    T_corr: object = array_field("correction T_W'W from W into the published frame W'", "float64", (4, 4))
    landmark_ids: object = array_field("ids of the window's triangulated landmarks (the frontend's)", "int64", ("N",))
    p_W: object = array_field("their positions in W [m]", "float64", ("N", 3))
    T_SC: object = array_field("each camera's extrinsic as the back end refines it (backend.refine_extrinsics), rig "
                               "order; none (0 of them) when it uses the calibration's", "float64", ("C", 4, 4),
                               default_factory=lambda: np.zeros((0, 4, 4)))
    time_offset_s: float = scalar_field("the camera-IMU time offset the back end estimates "
                                        "(backend.estimate_time_offset; 0 when off): an image stamped t was taken "
                                        "at IMU time t + offset [s]", default=0.0)
    status: str = scalar_field("'tracking' or 'imu_only' (the keyframe's), 'initialising' (no state yet) or 'reset' "
                               "(a restarted back end: forget the old window; no state)", default="tracking")
