"""Foxglove-viewable mirrors of sigmaslam messages (protobuf, ``foxglove-schemas-protobuf``).

:func:`mirror` turns one decoded message into zero or more ``(topic, protobuf message)`` pairs:

- ``MultiCameraFrame`` -> ``foxglove.RawImage`` (mono8) per camera on ``foxglove/<key>/<camera>``
- ``DepthFrame`` -> ``foxglove.RawImage`` (32FC1) of depth and of sigma on ``foxglove/<key>/depth|sigma``
- ``EstimatorState`` -> ``foxglove.PoseInFrame`` (``T_WS`` in frame ``W``) on ``foxglove/<key>``
- ``SubmapMesh`` -> ``foxglove.SceneUpdate`` with one entity ``submap<id>`` holding a
  ``TriangleListPrimitive`` posed at ``T_WM`` on ``foxglove/<key>``
- ``Landmarks`` -> ``foxglove.PointCloud`` (float32 x, y, z in frame ``W``) on ``foxglove/<key>``

Schemas are written as a serialized ``google.protobuf.FileDescriptorSet`` (schema encoding
``protobuf``), which is what Foxglove and the MCAP tools expect.
"""

from __future__ import annotations

import numpy as np
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf import descriptor_pb2
from google.protobuf.message import Message as ProtoMessage
from scipy.spatial.transform import Rotation

from shared import messages as m
from shared.codec import Message

PREFIX = "foxglove/"
SCHEMA_ENCODING = "protobuf"
MESSAGE_ENCODING = "protobuf"


def file_descriptor_set(proto_cls: type[ProtoMessage]) -> bytes:
    """Serialized FileDescriptorSet of ``proto_cls``'s file and all files it depends on."""
    fds = descriptor_pb2.FileDescriptorSet()
    seen: set[str] = set()

    def add(fd) -> None:
        if fd.name in seen:
            return
        seen.add(fd.name)
        for dep in fd.dependencies:
            add(dep)
        fd.CopyToProto(fds.file.add())

    add(proto_cls.DESCRIPTOR.file)
    return fds.SerializeToString()


def _stamp(proto_ts, stamp_ns: int) -> None:
    proto_ts.seconds, proto_ts.nanos = divmod(int(stamp_ns), 1_000_000_000)


def _set_pose(pose, T: np.ndarray) -> None:
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in T[:3, 3])
    x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()  # scalar-last (x, y, z, w)
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = x, y, z, w


def raw_image(image: np.ndarray, stamp_ns: int, frame_id: str) -> RawImage:
    """RawImage of a (H, W) uint8 (mono8) or float32 (32FC1) image."""
    encodings = {np.dtype(np.uint8): "mono8", np.dtype(np.float32): "32FC1"}
    encoding = encodings.get(image.dtype)
    if encoding is None or image.ndim != 2:
        raise ValueError(f"raw_image: expected a (H, W) uint8 or float32 image, got {image.dtype} {image.shape}")
    img = np.ascontiguousarray(image, dtype=image.dtype.newbyteorder("<"))
    out = RawImage(frame_id=frame_id, width=img.shape[1], height=img.shape[0], encoding=encoding,
                   step=img.shape[1] * img.itemsize, data=img.tobytes())
    _stamp(out.timestamp, stamp_ns)
    return out


def pose_in_frame(T: np.ndarray, stamp_ns: int, frame_id: str) -> PoseInFrame:
    out = PoseInFrame(frame_id=frame_id)
    _stamp(out.timestamp, stamp_ns)
    _set_pose(out.pose, T)
    return out


def scene_update(mesh: m.SubmapMesh) -> SceneUpdate:
    """SceneUpdate replacing entity ``submap<id>`` with the submap's triangle mesh, in frame W."""
    out = SceneUpdate()
    entity = out.entities.add(frame_id="W", id=f"submap{mesh.submap_id}")
    _stamp(entity.timestamp, mesh.header.stamp_ns)
    tri = entity.triangles.add()
    _set_pose(tri.pose, mesh.T_WM)
    for x, y, z in mesh.vertices_M.astype(np.float64).tolist():
        tri.points.add(x=x, y=y, z=z)
    tri.indices.extend(mesh.faces.reshape(-1).astype(np.int64).tolist())
    if len(mesh.vertex_colors) == len(mesh.vertices_M) and len(mesh.vertex_colors):
        for r, g, b in (mesh.vertex_colors.astype(np.float64) / 255.0).tolist():
            tri.colors.add(r=r, g=g, b=b, a=1.0)
    else:
        tri.color.r, tri.color.g, tri.color.b, tri.color.a = 0.7, 0.7, 0.7, 1.0
    return out


def point_cloud(points: np.ndarray, stamp_ns: int, frame_id: str) -> PointCloud:
    """PointCloud of (N, 3) points as little-endian float32 x, y, z (identity pose in ``frame_id``)."""
    pts = np.ascontiguousarray(np.asarray(points, np.float64).reshape(-1, 3), "<f4")
    out = PointCloud(frame_id=frame_id, point_stride=12, data=pts.tobytes())
    _stamp(out.timestamp, stamp_ns)
    out.pose.orientation.w = 1.0
    for i, name in enumerate("xyz"):
        out.fields.add(name=name, offset=4 * i, type=PackedElementField.FLOAT32)
    return out


def mirror(key: str, msg: Message) -> list[tuple[str, ProtoMessage]]:
    """Foxglove mirror messages of ``msg`` received on ``key`` (empty for types without a mirror)."""
    base = PREFIX + key
    stamp = msg.header.stamp_ns
    if isinstance(msg, m.MultiCameraFrame):
        return [(f"{base}/{name}", raw_image(img, stamp, name)) for name, img in zip(msg.camera_names, msg.images)]
    if isinstance(msg, m.DepthFrame):
        cam = msg.header.frame_id
        return [(f"{base}/depth", raw_image(msg.depth, stamp, cam)), (f"{base}/sigma", raw_image(msg.sigma, stamp, cam))]
    if isinstance(msg, m.EstimatorState):
        return [(base, pose_in_frame(msg.T_WS, stamp, msg.header.frame_id or "W"))]
    if isinstance(msg, m.SubmapMesh):
        return [(base, scene_update(msg))]
    if isinstance(msg, m.Landmarks):
        return [(base, point_cloud(msg.p_W, stamp, msg.header.frame_id or "W"))]
    return []
