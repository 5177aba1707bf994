"""A sigmaslam recording as a ROS 2 bag (MCAP storage) with standard messages, for RViz, Foxglove and ros2 bag.

    sigmaslam convert RUN/recording.mcap OUT_BAG --to ros2
    sigmaslam run DATASET --out DIR --ros2-bag OUT_BAG      (records, then converts at the end)

Written with ``rosbags`` (no ROS needed); message definitions are stored in the bag, so ``ros2 bag info/play``
and Foxglove read it. Topics and frames (docs/conventions.md, "ROS 2 output"):

| topic | type | from | frame_id -> child |
|---|---|---|---|
| ``/sigmaslam/odometry`` | nav_msgs/Odometry | estimator/state (causal, per frame) | ``world`` -> ``body`` |
| ``/tf`` | tf2_msgs/TFMessage | the same poses | ``world`` -> ``body`` |
| ``/tf_static`` | tf2_msgs/TFMessage | the depth camera in the body (first depth frame) | ``body`` -> ``depth_camera`` |
| ``/sigmaslam/path`` | nav_msgs/Path | estimator/trajectory_final (non-causal) | ``world`` |
| ``/sigmaslam/submap_points`` | sensor_msgs/PointCloud2 | map/submap vertices, in the world | ``world`` |
| ``/sigmaslam/submap_mesh`` | visualization_msgs/MarkerArray | map/submap triangles (TRIANGLE_LIST, id = submap id) | ``world`` |
| ``/sigmaslam/depth`` | sensor_msgs/Image 32FC1 [m], NaN invalid | depth/fused | ``depth_camera`` |
| ``/sigmaslam/depth_sigma`` | sensor_msgs/Image 32FC1 [m] | depth/fused sigma | ``depth_camera`` |
| ``/sigmaslam/depth/camera_info`` | sensor_msgs/CameraInfo | depth/fused K (rectified pinhole) | ``depth_camera`` |

``body`` is the IMU frame S; ``world`` is the estimator's W (gravity along -z). Odometry's twist is in ``body``
(the ROS convention: in child_frame_id); its pose covariance is in ROS order (x, y, z, roll, pitch, yaw):
the position block of the state's covariance and its rotation block (the estimator's rotation error is in the
body frame). Quaternions are written (x, y, z, w) as ROS wants. Stamps are the messages' header stamps; the bag's
log time is the recording's.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from shared.geometry import R_to_quat_wxyz, transform_points

TOPICS = {"odometry": "/sigmaslam/odometry", "path": "/sigmaslam/path", "points": "/sigmaslam/submap_points",
          "mesh": "/sigmaslam/submap_mesh", "depth": "/sigmaslam/depth", "sigma": "/sigmaslam/depth_sigma",
          "info": "/sigmaslam/depth/camera_info", "tf": "/tf", "tf_static": "/tf_static"}
FRAMES = {"world": "world", "body": "body", "depth": "depth_camera"}


class _Ros2:
    def __init__(self) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.ts = get_typestore(Stores.ROS2_HUMBLE)
        self.T = self.ts.types

    def stamp(self, ns: int):
        return self.T["builtin_interfaces/msg/Time"](sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))

    def header(self, ns: int, frame: str):
        return self.T["std_msgs/msg/Header"](stamp=self.stamp(ns), frame_id=frame)

    def pose(self, T: np.ndarray):
        q = R_to_quat_wxyz(np.asarray(T)[:3, :3])
        return self.T["geometry_msgs/msg/Pose"](position=self.T["geometry_msgs/msg/Point"](x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
                 orientation=self.T["geometry_msgs/msg/Quaternion"](x=float(q[1]), y=float(q[2]), z=float(q[3]),
                                                                    w=float(q[0])))

    def transform(self, ns: int, parent: str, child: str, T: np.ndarray):
        q = R_to_quat_wxyz(np.asarray(T)[:3, :3])
        tr = self.T["geometry_msgs/msg/Transform"](
            translation=self.T["geometry_msgs/msg/Vector3"](x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
            rotation=self.T["geometry_msgs/msg/Quaternion"](x=float(q[1]), y=float(q[2]), z=float(q[3]), w=float(q[0])))
        return self.T["geometry_msgs/msg/TransformStamped"](header=self.header(ns, parent), child_frame_id=child,
                                                            transform=tr)

    def vec3(self, v):
        return self.T["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def odometry(self, state):
        T = np.asarray(state.T_WS)
        cov = np.zeros((6, 6))
        c = np.asarray(state.covariance)
        if c.shape == (15, 15) and np.all(np.isfinite(c[:6, :6])):
            cov[:3, :3], cov[3:, 3:] = c[3:6, 3:6], c[:3, :3]  # [p, rot] from the state's [rot, p, ...]
            cov[:3, 3:], cov[3:, :3] = c[3:6, :3], c[:3, 3:6]
        v_S = T[:3, :3].T @ np.asarray(state.v_W)
        twist = self.T["geometry_msgs/msg/Twist"](linear=self.vec3(v_S), angular=self.vec3(np.zeros(3)))
        return self.T["nav_msgs/msg/Odometry"](
            header=self.header(state.header.stamp_ns, FRAMES["world"]), child_frame_id=FRAMES["body"],
            pose=self.T["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose(T), covariance=cov.ravel()),
            twist=self.T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)))

    def path(self, final):
        poses = [self.T["geometry_msgs/msg/PoseStamped"](header=self.header(int(t), FRAMES["world"]), pose=self.pose(T))
                 for t, T in zip(np.asarray(final.stamps_ns), np.asarray(final.T_WS))]
        last = int(final.stamps_ns[-1]) if len(final.stamps_ns) else final.header.stamp_ns
        return self.T["nav_msgs/msg/Path"](header=self.header(last, FRAMES["world"]), poses=poses)

    def cloud(self, ns: int, p_W: np.ndarray):
        F = self.T["sensor_msgs/msg/PointField"]
        fields = [F(name=n, offset=4 * i, datatype=F.FLOAT32, count=1) for i, n in enumerate("xyz")]
        data = np.ascontiguousarray(p_W, np.float32).view(np.uint8).ravel()
        return self.T["sensor_msgs/msg/PointCloud2"](header=self.header(ns, FRAMES["world"]), height=1,
                                                     width=len(p_W), fields=fields, is_bigendian=False, point_step=12,
                                                     row_step=12 * len(p_W), data=data, is_dense=True)

    def mesh(self, ns: int, sub):
        M = self.T["visualization_msgs/msg/Marker"]
        tri = np.asarray(sub.vertices_M, np.float64)[np.asarray(sub.faces).ravel()]
        pts = [self.T["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=float(z)) for x, y, z in tri]
        colour = self.T["std_msgs/msg/ColorRGBA"](r=0.7, g=0.7, b=0.75, a=1.0)
        marker = M(header=self.header(ns, FRAMES["world"]), ns="submap", id=int(sub.submap_id), type=M.TRIANGLE_LIST,
                   action=M.ADD, pose=self.pose(np.asarray(sub.T_WM)), scale=self.vec3([1, 1, 1]), color=colour,
                   lifetime=self.T["builtin_interfaces/msg/Duration"](sec=0, nanosec=0), frame_locked=False,
                   points=pts, colors=[], texture_resource="",
                   texture=self.T["sensor_msgs/msg/CompressedImage"](header=self.header(0, ""), format="", data=np.zeros(0, np.uint8)),
                   uv_coordinates=[], text="", mesh_resource="",
                   mesh_file=self.T["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, np.uint8)),
                   mesh_use_embedded_materials=False)
        return self.T["visualization_msgs/msg/MarkerArray"](markers=[marker])

    def image32(self, ns: int, a: np.ndarray):
        h, w = a.shape
        return self.T["sensor_msgs/msg/Image"](header=self.header(ns, FRAMES["depth"]), height=h, width=w,
                                               encoding="32FC1", is_bigendian=0, step=4 * w,
                                               data=np.ascontiguousarray(a, "<f4").view(np.uint8).ravel())

    def camera_info(self, ns: int, K: np.ndarray, shape):
        K = np.asarray(K, np.float64)
        P = np.hstack([K, np.zeros((3, 1))])
        roi = self.T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        return self.T["sensor_msgs/msg/CameraInfo"](header=self.header(ns, FRAMES["depth"]), height=shape[0],
                                                    width=shape[1], distortion_model="plumb_bob", d=np.zeros(5),
                                                    k=K.ravel(), r=np.eye(3).ravel(), p=P.ravel(), binning_x=0,
                                                    binning_y=0, roi=roi)


def recording_to_ros2(recording: str | Path, out: str | Path, depth_every: int = 1) -> dict[str, int]:
    """Write the ROS 2 bag OUT (a folder, MCAP storage) from a sigmaslam recording; returns message counts per
    topic. ``depth_every``: keep every n-th depth frame (depth images are the bulk of a bag)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from services.recorder.mcap_reader import read_recording
    from shared import messages as m

    out = Path(out)
    if out.exists():
        raise FileExistsError(f"{out}: already exists (a ROS 2 bag is a new folder)")
    r = _Ros2()
    counts = {k: 0 for k in TOPICS}
    kinds = {m.EstimatorState: "state", m.FinalTrajectory: "final", m.SubmapMesh: "submap", m.DepthFrame: "depth"}
    types = {"odometry": "nav_msgs/msg/Odometry", "path": "nav_msgs/msg/Path", "points": "sensor_msgs/msg/PointCloud2",
             "mesh": "visualization_msgs/msg/MarkerArray", "depth": "sensor_msgs/msg/Image",
             "sigma": "sensor_msgs/msg/Image", "info": "sensor_msgs/msg/CameraInfo", "tf": "tf2_msgs/msg/TFMessage",
             "tf_static": "tf2_msgs/msg/TFMessage"}
    n_depth = 0
    with Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {k: w.add_connection(TOPICS[k], types[k], typestore=r.ts) for k in TOPICS}

        def put(key, t, msg):
            w.write(conns[key], int(t), r.ts.serialize_cdr(msg, types[key]))
            counts[key] += 1

        for key_expr, t, msg in read_recording(recording):
            kind = kinds.get(type(msg))
            if kind == "state":
                if msg.status in ("initialising", "reset"):
                    continue
                put("odometry", t, r.odometry(msg))
                put("tf", t, r.T["tf2_msgs/msg/TFMessage"](transforms=[
                    r.transform(msg.header.stamp_ns, FRAMES["world"], FRAMES["body"], np.asarray(msg.T_WS))]))
            elif kind == "final" and len(msg.stamps_ns):
                put("path", t, r.path(msg))
            elif kind == "submap" and len(msg.vertices_M):
                ns = msg.header.stamp_ns
                put("points", t, r.cloud(ns, transform_points(np.asarray(msg.T_WM), np.asarray(msg.vertices_M, np.float64))))
                put("mesh", t, r.mesh(ns, msg))
            elif kind == "depth" and msg.source in ("fused", "mvs") and "depth/fused" in key_expr:
                n_depth += 1
                if (n_depth - 1) % depth_every:
                    continue
                ns = msg.header.stamp_ns
                if counts["tf_static"] == 0:
                    put("tf_static", t, r.T["tf2_msgs/msg/TFMessage"](transforms=[
                        r.transform(ns, FRAMES["body"], FRAMES["depth"], np.asarray(msg.T_SC))]))
                put("depth", t, r.image32(ns, np.asarray(msg.depth)))
                put("sigma", t, r.image32(ns, np.asarray(msg.sigma)))
                put("info", t, r.camera_info(ns, msg.K, np.asarray(msg.depth).shape))
    return counts
