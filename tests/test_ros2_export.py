"""A sigmaslam recording exported as a ROS 2 bag with standard messages: read back with rosbags (types, counts,
stamps, frames, poses as quaternions x,y,z,w, point clouds and meshes in the world, depth as 32FC1) and with
mcap-ros2-support's decoder (the schemas in the file are enough to decode it, as Foxglove does)."""
import numpy as np
import pytest

from services.recorder.mcap_writer import RecordingWriter
from shared import messages as m
from shared.geometry import make_T, so3_exp
from services.app.datasets.ros2_export import TOPICS, recording_to_ros2

pytestmark = pytest.mark.unit
NS = "sigmaslam/robot0/"


def _recording(path):
    rng = np.random.default_rng(0)
    poses = [make_T(so3_exp(np.array([0.0, 0.0, 0.1 * i])), np.array([0.1 * i, 0.0, 1.0])) for i in range(5)]
    with RecordingWriter(path) as w:
        for i, T in enumerate(poses):
            t = 1_000_000_000 + i * 50_000_000
            cov = np.eye(15) * 1e-4
            cov[3:6, 3:6] *= 4
            status = "initialising" if i == 0 else "tracking"
            w.write_message(NS + "estimator/state", m.EstimatorState(
                header=m.Header(stamp_ns=t, frame_id="W"), T_WS=T, v_W=np.array([1.0, 0.0, 0.0]), gyro_bias=np.zeros(3),
                acc_bias=np.zeros(3), covariance=cov, status=status), log_time_ns=t)
            depth = np.full((8, 12), 2.0, np.float32)
            depth[0, 0] = np.nan
            w.write_message(NS + "depth/fused", m.DepthFrame(
                header=m.Header(stamp_ns=t, frame_id="cam0"), depth=depth, sigma=depth * 0.01,
                K=np.array([[10.0, 0, 6], [0, 10.0, 4], [0, 0, 1]]), T_WC=T, T_SC=make_T(np.eye(3), np.array([0.0, 0.1, 0.0])),
                source="fused"), log_time_ns=t + 1)
        verts = rng.random((6, 3)).astype(np.float32)
        w.write_message(NS + "map/submap", m.SubmapMesh(
            header=m.Header(stamp_ns=1_200_000_000, frame_id="W"), submap_id=3, T_WM=poses[2], vertices_M=verts,
            faces=np.array([[0, 1, 2], [3, 4, 5]], np.int32), vertex_colors=np.zeros((0, 3), np.uint8)),
            log_time_ns=1_200_000_002)
        w.write_message(NS + "estimator/trajectory_final", m.FinalTrajectory(
            header=m.Header(stamp_ns=1_300_000_000, frame_id="W"), stamps_ns=np.array([1, 2, 3], np.int64) * 10**9,
            T_WS=np.stack(poses[:3]), keyframes=3, loops_proposed=0, loops_verified=0, loops_accepted=0,
            relocalisations=0), log_time_ns=1_300_000_000)
    return poses, verts


def test_recording_to_ros2_bag_reads_back(tmp_path):
    from rosbags.highlevel import AnyReader

    poses, verts = _recording(tmp_path / "rec.mcap")
    counts = recording_to_ros2(tmp_path / "rec.mcap", tmp_path / "bag")
    # the initialising state is left out; the final trajectory sends one more map -> odom
    assert counts["odom"] == 4 and counts["tf"] == 5
    assert counts["depth"] == counts["sigma"] == counts["info"] == 5 and counts["depth_static"] == 1
    assert counts["map_cloud"] == counts["map_mesh"] == counts["path"] == 1 and counts["tf_static"] >= 1
    with pytest.raises(FileExistsError):
        recording_to_ros2(tmp_path / "rec.mcap", tmp_path / "bag")
    got = {}
    with AnyReader([tmp_path / "bag"]) as r:
        types = {c.topic: c.msgtype for c in r.connections}
        assert types[TOPICS["odom"]] == "nav_msgs/msg/Odometry" and types["/tf"] == "tf2_msgs/msg/TFMessage"
        assert TOPICS["odom"] == "/sigmaslam/odom" and TOPICS["tf_static"] == "/tf_static"
        for conn, t, raw in r.messages():
            got.setdefault(conn.topic, []).append((t, r.deserialize(raw, conn.msgtype)))
    # every message is logged at its header stamp (sensor time), not at the recording's clock
    for topic, items in got.items():
        for t, msg in items:
            h = msg.transforms[0].header if topic.startswith("/tf") else msg.header
            assert t == h.stamp.sec * 10**9 + h.stamp.nanosec, topic
    odo = got[TOPICS["odom"]][1][1]
    assert (odo.header.frame_id, odo.child_frame_id) == ("odom", "base_link")
    assert odo.header.stamp.sec == 1 and odo.header.stamp.nanosec == 100_000_000
    q = odo.pose.pose.orientation  # yaw 0.2 rad about z, written x, y, z, w
    assert np.allclose([q.x, q.y, q.z, q.w], [0, 0, np.sin(0.1), np.cos(0.1)])
    assert odo.pose.pose.position.x == pytest.approx(0.2)
    cov = odo.pose.covariance.reshape(6, 6)
    assert cov[0, 0] == pytest.approx(4e-4) and cov[3, 3] == pytest.approx(1e-4)  # position block first
    v = odo.twist.twist.linear  # body frame: world x velocity seen from a body yawed by 0.2 rad
    assert [v.x, v.y] == pytest.approx([np.cos(0.2), -np.sin(0.2)])
    tf = got["/tf"][0][1].transforms
    assert [(x.header.frame_id, x.child_frame_id) for x in tf] == [("map", "odom"), ("odom", "base_link")]
    static = next(x for _, s in got["/tf_static"] for x in s.transforms if x.child_frame_id == "depth_camera")
    assert static.child_frame_id == "depth_camera" and static.transform.translation.y == pytest.approx(0.1)
    cloud = got[TOPICS["map_cloud"]][0][1]
    assert cloud.header.frame_id == "map"
    pts = np.frombuffer(bytes(cloud.data), np.float32).reshape(-1, 3)
    expect = verts.astype(np.float64) @ poses[2][:3, :3].T + poses[2][:3, 3]
    assert cloud.width == 6 and np.allclose(pts, expect, atol=1e-6)
    marker = got[TOPICS["map_mesh"]][0][1]
    assert marker.type == 11 and marker.id == 3 and len(marker.points) == 6  # TRIANGLE_LIST, 2 triangles
    path = got[TOPICS["path"]][0][1]
    assert len(path.poses) == 3 and path.poses[2].header.stamp.sec == 3 and path.header.frame_id == "map"
    img = got[TOPICS["depth"]][0][1]
    depth = np.frombuffer(bytes(img.data), "<f4").reshape(img.height, img.width)
    assert img.encoding == "32FC1" and np.isnan(depth[0, 0]) and depth[1, 1] == 2.0
    info = got[TOPICS["info"]][0][1]
    assert info.k[0] == 10.0 and info.header.frame_id == "depth_camera"


def test_the_bag_decodes_with_its_own_schemas(tmp_path):
    """What Foxglove does: decode every message from the schemas stored in the MCAP file alone."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    _recording(tmp_path / "rec.mcap")
    recording_to_ros2(tmp_path / "rec.mcap", tmp_path / "bag")
    files = list((tmp_path / "bag").glob("*.mcap"))
    assert len(files) == 1 and (tmp_path / "bag" / "metadata.yaml").is_file()
    seen = {}
    with open(files[0], "rb") as f:
        for schema, channel, message, decoded in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            seen[channel.topic] = (schema.name, decoded)
    assert seen[TOPICS["odom"]][0] == "nav_msgs/msg/Odometry"
    assert seen[TOPICS["map_mesh"]][0] == "visualization_msgs/msg/Marker"
    assert seen[TOPICS["path"]][1].poses[0].header.stamp.sec == 1
