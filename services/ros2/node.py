"""The ROS 2 face as a process node (``sigmaslam ros2``): sigmaslam's results as ROS 2 topics on Zenoh, in rmw_zenoh's
wire format (shared/ros2_wire.py), so that ``ros2 topic echo`` and RViz on an rmw_zenoh host see them with no
bridge.

Per causal state: ``odom`` (nav_msgs/Odometry, odom -> base_link with its covariance) and ``tf`` (map -> odom, the
loop-closure correction, and odom -> base_link). Per keyframe update: ``path`` (the keyframes in map) and a new
map -> odom: the keyframes' loop-closed pose times the inverse of the causal pose of the same frame; at the end of
the stream the final trajectory does the same. ``landmarks`` per landmark update; ``map_cloud`` (every submap's
surface points) and ``map_mesh`` (a TRIANGLE_LIST marker per changed submap) at most every
``ros2.cloud_period_s`` / ``mesh_period_s``; ``tf_static`` (base_link -> each camera and the IMU) at the start and
every ``ros2.static_period_s``; ``map_grid`` (nav_msgs/OccupancyGrid) per map/grid message. What it sends goes through a sink (``sink(output, cdr_bytes)``): the Zenoh
participant of transport/rmw_zenoh.py in the process, a list in tests. Counters per output in ``stats/ros2``.
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict
from typing import Callable

import numpy as np

from shared import messages as m
from shared import topics
from shared.dataflow import Input, ProcessNode, RejectedMessage
from shared.geometry import inv_T, transform_points
from shared.process_description import ProcessDescription, ProcessStartError, Scheduling, Start

log = logging.getLogger("sigmaslam.ros2")

# output -> ROS 2 type (the key of ros2.topics)
OUTPUT_TYPES = {"odom": "nav_msgs/msg/Odometry", "tf": "tf2_msgs/msg/TFMessage", "tf_static": "tf2_msgs/msg/TFMessage",
                "path": "nav_msgs/msg/Path", "landmarks": "sensor_msgs/msg/PointCloud2",
                "map_cloud": "sensor_msgs/msg/PointCloud2", "map_grid": "nav_msgs/msg/OccupancyGrid",
                "map_mesh": "visualization_msgs/msg/Marker"}
CAUSAL_KEPT = 4096  # causal poses kept by stamp, to pair with the keyframes' loop-closed ones


class Ros2Node(ProcessNode):
    name = "ros2"
    inputs = (Input(topics.STATE, "on_state", policy="all", depth=256, note="odom, tf"),
              Input(topics.KEYFRAMES, "on_keyframes", note="path; map -> odom"),
              Input(topics.TRAJECTORY_FINAL, "on_final", note="path and map -> odom at the end"),
              Input(topics.LANDMARKS, "on_landmarks", note="landmarks"),
              Input(topics.SUBMAP, "on_submap", policy="all", depth=64, note="map_cloud, map_mesh"),
              Input(topics.MAP_GRID, "on_grid", note="map_grid"))
    outputs = ()

    def __init__(self, rcfg, cameras, sink: Callable[[str, bytes, int], None], clock=time.monotonic,
                 on_close: Callable[[], None] | None = None) -> None:
        from shared.ros2_msgs import Frames, RosMessages
        from shared.ros2_wire import type_store

        self.rcfg, self.sink, self.clock, self.on_close = rcfg, sink, clock, on_close
        self.frames = Frames(map=rcfg.map_frame, odom=rcfg.odom_frame, base_link=rcfg.base_frame, imu=rcfg.imu_frame)
        self.ros = RosMessages(type_store(), self.frames, np.asarray(rcfg.T_BS, np.float64).reshape(4, 4))
        self.cameras = list(cameras or [])
        self.T_map_odom = np.eye(4)
        self.causal: OrderedDict[int, np.ndarray] = OrderedDict()
        self.submaps: dict[int, m.SubmapMesh] = {}
        self.changed: set[int] = set()
        self.cloud_dirty = False
        self.next_cloud = self.next_mesh = self.next_static = clock()
        self.sent = {k: 0 for k in OUTPUT_TYPES}
        self.last_stamp_ns = 0

    def _send(self, output: str, msg, stamp_ns: int) -> None:
        self.sink(output, self.ros.cdr(msg, OUTPUT_TYPES[output]), int(stamp_ns))
        self.sent[output] += 1

    def counters(self) -> dict:
        return {f"sent_{k}": (lambda k=k: self.sent[k]) for k in OUTPUT_TYPES}

    # ------------------------------------------------------------------ handlers

    def on_state(self, msg: m.EstimatorState) -> None:
        if msg.status in ("initialising", "reset"):
            if msg.status == "reset":  # a restarted estimator: its poses of before no longer pair
                self.causal.clear()
            return
        T_WS = np.asarray(msg.T_WS, np.float64)
        if T_WS.shape != (4, 4) or not np.all(np.isfinite(T_WS)):
            raise RejectedMessage("a state with a non-finite pose")
        ns = int(msg.header.stamp_ns)
        self.last_stamp_ns = max(self.last_stamp_ns, ns)
        self.causal[ns] = T_WS
        while len(self.causal) > CAUSAL_KEPT:
            self.causal.popitem(last=False)
        with self.timer("odom_tf"):
            f = self.frames
            self._send("odom", self.ros.odometry(msg), ns)
            self._send("tf", self.ros.tf([self.ros.transform(ns, f.map, f.odom, self.T_map_odom),
                                          self.ros.transform(ns, f.odom, f.base_link, self.ros.base_pose(T_WS))]), ns)

    def _correct(self, stamps_ns, T_WS) -> None:
        """map -> odom from the newest frame that has both a loop-closed pose (``T_WS``) and a causal one."""
        for t, T in zip(reversed(np.asarray(stamps_ns).tolist()), reversed(np.asarray(T_WS).reshape(-1, 4, 4))):
            causal = self.causal.get(int(t))
            if causal is not None:
                self.T_map_odom = np.asarray(T, np.float64) @ inv_T(causal)
                return

    def on_keyframes(self, msg: m.Keyframes) -> None:
        if not len(msg.stamps_ns):
            return
        self._correct(msg.stamps_ns, msg.T_WS)
        self._send("path", self.ros.path(msg.stamps_ns, msg.T_WS, self.frames.map), int(msg.stamps_ns[-1]))

    def on_final(self, msg: m.FinalTrajectory) -> None:
        if not len(msg.stamps_ns):
            return
        self._correct(msg.stamps_ns, msg.T_WS)
        f = self.frames
        ns = int(msg.stamps_ns[-1])
        self._send("path", self.ros.path(msg.stamps_ns, msg.T_WS, self.frames.map), ns)
        self._send("tf", self.ros.tf([self.ros.transform(ns, f.map, f.odom, self.T_map_odom)]), ns)

    def on_landmarks(self, msg: m.Landmarks) -> None:
        p = np.asarray(msg.p_W, np.float64).reshape(-1, 3)
        ns = int(msg.header.stamp_ns)
        self._send("landmarks", self.ros.cloud(ns, p[np.all(np.isfinite(p), axis=1)], self.frames.odom), ns)

    def on_grid(self, msg: m.OccupancyGrid2D) -> None:
        cells = np.asarray(msg.cells)
        if cells.ndim != 2 or not msg.resolution_m > 0:
            raise RejectedMessage(f"a grid of shape {cells.shape}, resolution {msg.resolution_m}")
        with self.timer("map_grid"):
            self._send("map_grid", self.ros.occupancy_grid(msg, self.frames.map), msg.header.stamp_ns)

    def on_submap(self, msg: m.SubmapMesh) -> None:
        self.submaps[int(msg.submap_id)] = msg
        self.changed.add(int(msg.submap_id))
        self.cloud_dirty = True

    # ------------------------------------------------------------------ periodic outputs

    def tick(self) -> list:
        now = self.clock()
        if now >= self.next_static and self.last_stamp_ns > 0:  # stamped by the sensor clock: after a first state
            self.next_static = now + self.rcfg.static_period_s
            self.send_static()
        if self.cloud_dirty and now >= self.next_cloud:
            self.next_cloud, self.cloud_dirty = now + self.rcfg.cloud_period_s, False
            with self.timer("map_cloud"):
                self.send_cloud()
        if self.changed and now >= self.next_mesh:
            self.next_mesh = now + self.rcfg.mesh_period_s
            with self.timer("map_mesh"):
                for sid in sorted(self.changed):
                    s = self.submaps[sid]
                    ns = int(s.header.stamp_ns)
                    self.sink("map_mesh", self.ros.mesh_marker_cdr(ns, sid, s.T_WM, s.vertices_M, s.faces,
                                                                   self.frames.map), ns)
                    self.sent["map_mesh"] += 1
                self.changed.clear()
        return []

    def send_static(self) -> None:
        """base_link -> the IMU and each camera of the rig."""
        f, ns = self.frames, self.last_stamp_ns
        out = [self.ros.transform(ns, f.base_link, f.imu, self.ros.T_BS)]
        out += [self.ros.transform(ns, f.base_link, c.name, self.ros.T_BS @ np.asarray(c.T_SC)) for c in self.cameras]
        self._send("tf_static", self.ros.tf(out), ns)

    def send_cloud(self) -> None:
        parts = [transform_points(np.asarray(s.T_WM), np.asarray(s.vertices_M, np.float64))
                 for s in self.submaps.values() if len(s.vertices_M)]
        p = np.concatenate(parts) if parts else np.zeros((0, 3))
        if len(p) > self.rcfg.max_cloud_points:
            p = p[::int(np.ceil(len(p) / self.rcfg.max_cloud_points))]
        ns = max(int(s.header.stamp_ns) for s in self.submaps.values()) if self.submaps else 0
        self._send("map_cloud", self.ros.cloud(ns, p, self.frames.map), ns)

    def close(self) -> list:
        self.tick()
        if self.cloud_dirty:
            self.send_cloud()
        log.info("ros2: sent %s", ", ".join(f"{k} {v}" for k, v in self.sent.items()))
        if self.on_close is not None:
            self.on_close()
        return []


def _build(cfg, start: Start) -> Ros2Node:
    from transport.rmw_zenoh import RosParticipant, participant_config

    rcfg = cfg.ros2
    try:
        cameras = start.rig(cfg)
    except ProcessStartError as exc:
        log.warning("no rig for tf_static's cameras (%s): the IMU only", exc)
        cameras = []
    try:
        ros = RosParticipant(participant_config(cfg.transport, rcfg.connect), rcfg.domain_id, rcfg.namespace, rcfg.node_name,
                             rcfg.attachment).open()
    except Exception as exc:  # zenoh raises its own error type for an unreachable or malformed endpoint
        raise ProcessStartError(f"cannot join the ROS 2 network {rcfg.connect or cfg.transport.connect}: {exc}") from exc
    from shared.ros2_wire import Qos

    pubs = {k: ros.publisher(getattr(rcfg.topics, k), t, Qos(transient_local=True, depth=1) if k == "tf_static" else Qos())
            for k, t in OUTPUT_TYPES.items()}
    node = Ros2Node(rcfg, cameras, lambda k, b, ns: pubs[k].put(b), on_close=ros.close)
    node.publishers = pubs
    return node


def _ready(node, cfg) -> str:
    return (f"ros2: node {cfg.ros2.node_name} (namespace '{cfg.ros2.namespace or '/'}') in domain "
            f"{cfg.ros2.domain_id}; odom on {node.publishers['odom'].key}")


DESCRIPTION = ProcessDescription(
    name="ros2", node=Ros2Node, build=_build, ready=_ready, switch="ros2.enabled",
    scheduling=Scheduling(nice=10),
    help="the ROS 2 face: odometry, tf, path, clouds, mesh, grid as ROS 2 topics on Zenoh (rmw_zenoh wire format)")
