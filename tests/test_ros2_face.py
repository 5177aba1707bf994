"""The ROS 2 face (issue 58): rmw_zenoh's names and bytes (shared/ros2_wire.py), the messages it builds
(services/ros2/node.py, decoded back with rosbags' Jazzy store), and ``sigmaslam ros2`` as a process read by an
independent Zenoh subscriber on the keys a ROS 2 subscriber uses, with its liveliness tokens found by a query."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import yaml

from shared import messages as m
from shared import ros2_wire as wire
from shared import topics
from shared.camera import CameraCalib, CameraModel
from shared.config import to_dict
from shared.geometry import inv_T, make_T, quat_wxyz_to_R, so3_exp
from shared.messages import Header

JAZZY_ODOM_HASH = "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0"


def _pose(i: int) -> np.ndarray:
    return make_T(so3_exp(np.array([0.01 * i, -0.02, 0.03 * i])), np.array([0.1 * i, 0.05 * i, 1.0 + 0.01 * i]))


def _state(i: int, status: str = "tracking") -> m.EstimatorState:
    cov = np.diag(np.arange(1.0, 16.0)) * 1e-4
    return m.EstimatorState(header=Header(stamp_ns=1_000_000_000 + i * 50_000_000, seq=i, frame_id="W"), T_WS=_pose(i),
                            v_W=np.array([0.1, 0.2, 0.3]), gyro_bias=np.zeros(3), acc_bias=np.zeros(3),
                            covariance=cov, status=status)


def _T_of(pose) -> np.ndarray:
    q = pose.orientation
    return make_T(quat_wxyz_to_R(np.array([q.w, q.x, q.y, q.z])), np.array([pose.position.x, pose.position.y,
                                                                           pose.position.z]))


def _T_of_tf(tr) -> np.ndarray:
    q, t = tr.transform.rotation, tr.transform.translation
    return make_T(quat_wxyz_to_R(np.array([q.w, q.x, q.y, q.z])), np.array([t.x, t.y, t.z]))


# ----------------------------------------------------------------------------- names and bytes

@pytest.mark.unit
def test_data_keys_and_tokens_follow_rmw_zenoh():
    assert wire.type_hash("nav_msgs/msg/Odometry") == JAZZY_ODOM_HASH
    assert wire.data_key(0, wire.fq_topic("/robot0", "odom"), "nav_msgs/msg/Odometry") == \
        f"0/robot0/odom/nav_msgs::msg::dds_::Odometry_/{JAZZY_ODOM_HASH}"
    assert wire.fq_topic("", "tf") == "/tf" and wire.fq_topic("/robot0", "/tf") == "/tf"
    assert wire.split_data_key(f"7/a/b/odom/nav_msgs::msg::dds_::Odometry_/{JAZZY_ODOM_HASH}") == \
        (7, "/a/b/odom", "nav_msgs::msg::dds_::Odometry_", JAZZY_ODOM_HASH)
    assert wire.node_token(3, "abc", 0, "", "sigmaslam") == "@ros2_lv/3/abc/0/0/NN/%/%/sigmaslam"
    tok = wire.entity_token(0, "abc", 0, 5, "MP", "/robot0", "sigmaslam", "/robot0/odom", "nav_msgs/msg/Odometry")
    assert tok == f"@ros2_lv/0/abc/0/5/MP/%/%robot0/sigmaslam/%robot0%odom/nav_msgs::msg::dds_::Odometry_/" \
                  f"{JAZZY_ODOM_HASH}/::,:,:,:,,"
    assert wire.Qos(transient_local=True, depth=1).keyexpr() == ":1:,1:,:,:,,"
    assert len(wire.gid_of(tok)) == 16 and wire.gid_of(tok) != wire.gid_of(tok.replace("/5/", "/6/"))
    with pytest.raises(wire.WireError):
        wire.split_data_key("odom/nav_msgs")
    with pytest.raises(wire.WireError):
        wire.dds_type_name("Odometry")


@pytest.mark.unit
def test_attachment_is_zenoh_serialisation_in_both_layouts():
    from zenoh.ext import Int64, z_serialize

    gid = bytes(range(16, 32))
    a = wire.Attachment(42, 1_700_000_000_123_456_789, gid)
    # what rmw_zenoh's Jazzy releases write: each value after its name, in zenoh-ext's serialisation
    expected = z_serialize(("sequence_number", Int64(42), "source_timestamp", Int64(1_700_000_000_123_456_789),
                            "source_gid", gid)).to_bytes()
    assert a.encode("labelled") == expected and len(expected) == 77
    assert a.encode("plain") == z_serialize((Int64(42), Int64(1_700_000_000_123_456_789), gid)).to_bytes()
    for layout in wire.ATTACHMENT_LAYOUTS:
        assert wire.decode_attachment(a.encode(layout)) == a
    for bad in (a.encode()[:-3], a.encode() + b"\0", a.encode().replace(b"source_gid", b"source_gix"), b""):
        with pytest.raises(wire.WireError):
            wire.decode_attachment(bad)


# ----------------------------------------------------------------------------- the node's messages

def _node(**rcfg):
    from services.ros2.config import Ros2Config
    from services.ros2.node import Ros2Node

    sent: list[tuple[str, bytes]] = []
    stamps: list[int] = []
    cam = CameraCalib("cam0", CameraModel(width=64, height=48, fx=50, fy=50, cx=32, cy=24),
                      make_T(so3_exp(np.array([0.0, 0.1, 0.0])), np.array([0.02, -0.06, 0.01])))
    clock = [0.0]
    node = Ros2Node(Ros2Config(**rcfg), [cam], lambda k, b, ns: (sent.append((k, b)), stamps.append(ns)),
                    clock=lambda: clock[0])
    node.stamps = stamps
    return node, sent, cam, clock


def _decoded(sent, output):
    from services.ros2.node import OUTPUT_TYPES

    ts = wire.type_store()
    return [ts.deserialize_cdr(b, OUTPUT_TYPES[k]) for k, b in sent if k == output]


@pytest.mark.unit
def test_odometry_and_tf_carry_the_causal_pose_and_the_loop_correction():
    node, sent, cam, clock = _node()
    for i in range(5):
        node.on_state(_state(i))
    node.on_state(_state(9, status="initialising"))  # not a pose: nothing sent
    odom = _decoded(sent, "odom")
    assert len(odom) == 5
    for i, o in enumerate(odom):
        assert o.header.frame_id == "odom" and o.child_frame_id == "base_link"
        assert o.header.stamp.sec == 1 and o.header.stamp.nanosec == i * 50_000_000
        np.testing.assert_allclose(_T_of(o.pose.pose), _pose(i), atol=1e-12)
        cov = o.pose.covariance.reshape(6, 6)  # ROS order: position first (the state's 3..5), then rotation (0..2)
        np.testing.assert_allclose(np.diag(cov), np.array([4, 5, 6, 1, 2, 3]) * 1e-4)
        np.testing.assert_allclose(o.twist.twist.linear.x, (_pose(i)[:3, :3].T @ [0.1, 0.2, 0.3])[0])
    # a loop closure moves the keyframes: map -> odom becomes loop-closed x inverse(causal) of the same frame
    delta = make_T(so3_exp(np.array([0.0, 0.0, 0.2])), np.array([0.3, -0.1, 0.05]))
    kf = [1, 3]
    node.on_keyframes(m.Keyframes(header=Header(stamp_ns=_state(3).header.stamp_ns), ids=np.array(kf),
                                  stamps_ns=np.array([_state(i).header.stamp_ns for i in kf]),
                                  T_WS=np.array([delta @ _pose(i) for i in kf])))
    node.on_state(_state(5))
    tf = _decoded(sent, "tf")[-1].transforms
    assert [(t.header.frame_id, t.child_frame_id) for t in tf] == [("map", "odom"), ("odom", "base_link")]
    np.testing.assert_allclose(_T_of_tf(tf[0]), delta, atol=1e-12)
    np.testing.assert_allclose(_T_of_tf(tf[1]), _pose(5), atol=1e-12)
    # map -> odom o odom -> base_link: the loop-closed pose of the frame
    np.testing.assert_allclose(_T_of_tf(tf[0]) @ _T_of_tf(tf[1]), delta @ _pose(5), atol=1e-12)
    path = _decoded(sent, "path")[-1]
    assert path.header.frame_id == "map" and len(path.poses) == 2
    np.testing.assert_allclose(_T_of(path.poses[1].pose), delta @ _pose(3), atol=1e-12)


@pytest.mark.unit
def test_base_link_offset_static_tf_clouds_and_mesh():
    T_BS = make_T(so3_exp(np.array([0.0, 0.0, np.pi / 2])), np.array([0.1, 0.0, 0.2]))
    node, sent, cam, clock = _node(T_BS=tuple(T_BS.ravel()))
    node.on_state(_state(2))
    o = _decoded(sent, "odom")[0]
    np.testing.assert_allclose(_T_of(o.pose.pose), _pose(2) @ inv_T(T_BS), atol=1e-12)  # T_W_B = T_WS T_SB
    node.tick()
    static = _decoded(sent, "tf_static")[0].transforms
    assert [(t.header.frame_id, t.child_frame_id) for t in static] == [("base_link", "imu"), ("base_link", "cam0")]
    np.testing.assert_allclose(_T_of_tf(static[0]), T_BS, atol=1e-12)
    np.testing.assert_allclose(_T_of_tf(static[1]), T_BS @ cam.T_SC, atol=1e-12)
    p = np.array([[1.0, 2.0, 3.0], [np.nan, 0.0, 0.0], [-1.0, 0.5, 2.0]])
    node.on_landmarks(m.Landmarks(header=Header(stamp_ns=5), ids=np.arange(3), p_W=p,
                                  num_observations=np.ones(3, np.int32), last_seen_ns=np.zeros(3, np.int64)))
    lm = _decoded(sent, "landmarks")[0]
    assert lm.header.frame_id == "odom" and lm.width == 2
    np.testing.assert_allclose(np.frombuffer(lm.data.tobytes(), np.float32).reshape(-1, 3), p[[0, 2]])
    T_WM = make_T(so3_exp(np.array([0.1, 0.0, 0.0])), np.array([1.0, 0.0, 0.0]))
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    node.on_submap(m.SubmapMesh(header=Header(stamp_ns=7), submap_id=4, T_WM=T_WM, vertices_M=v,
                                faces=np.array([[0, 1, 2], [0, 2, 3]], np.int32), vertex_colors=np.zeros((0, 3), np.uint8)))
    clock[0] += 10.0
    node.tick()
    cloud = _decoded(sent, "map_cloud")[0]
    assert cloud.header.frame_id == "map"
    np.testing.assert_allclose(np.frombuffer(cloud.data.tobytes(), np.float32).reshape(-1, 3),
                               (T_WM[:3, :3] @ v.T).T + T_WM[:3, 3], atol=1e-6)
    mk = _decoded(sent, "map_mesh")[0]
    assert mk.type == 11 and mk.id == 4 and len(mk.points) == 6  # TRIANGLE_LIST: 3 points per face
    np.testing.assert_allclose(_T_of(mk.pose), T_WM, atol=1e-12)
    assert [mk.points[i].z for i in range(6)] == [0, 0, 0, 0, 0, 1]


@pytest.mark.unit
def test_mesh_marker_written_by_numpy_is_rosbags_own_cdr():
    from shared.ros2_msgs import RosMessages

    r = RosMessages(wire.type_store())
    rng = np.random.default_rng(1)
    for nv, nf in ((3, 1), (50, 77), (400, 1000)):
        v = rng.random((nv, 3)).astype(np.float32)
        f = rng.integers(0, nv, (nf, 3)).astype(np.int32)
        T = make_T(so3_exp(rng.normal(size=3)), rng.normal(size=3))
        for frame in ("map", "a_longer_frame_name"):  # another string length shifts what follows the points
            ours = r.mesh_marker_cdr(123_456_789, nf, T, v, f, frame)
            assert ours == r.cdr(r.mesh_marker(123_456_789, nf, T, v, f, frame), "visualization_msgs/msg/Marker")


@pytest.mark.unit
def test_occupancy_grid_keeps_rows_values_and_origin():
    node, sent, cam, clock = _node()
    cells = np.array([[0, 100, 255], [50, 255, 0]], np.uint8)  # 2 rows (y) x 3 columns (x)
    node.on_grid(m.OccupancyGrid2D(header=Header(stamp_ns=3_500_000_000, frame_id="W"), resolution_m=0.05,
                                   origin_xy_m=np.array([-1.0, 2.0]), z_band_m=np.array([0.1, 1.5]), cells=cells))
    g = _decoded(sent, "map_grid")[0]
    assert g.header.frame_id == "map" and (g.header.stamp.sec, g.header.stamp.nanosec) == (3, 500_000_000)
    assert (g.info.width, g.info.height) == (3, 2) and g.info.resolution == pytest.approx(0.05)
    assert (g.info.origin.position.x, g.info.origin.position.y, g.info.origin.position.z) == (-1.0, 2.0, 0.1)
    assert g.data.tolist() == [0, 100, -1, 50, -1, 0]  # row-major from the lowest y, unknown as -1
    with pytest.raises(Exception, match="shape"):
        node.on_grid(m.OccupancyGrid2D(header=Header(stamp_ns=1), resolution_m=0.05, origin_xy_m=np.zeros(2),
                                       z_band_m=np.zeros(2), cells=np.zeros(3, np.uint8)))


# ----------------------------------------------------------------------------- the process

@pytest.mark.service
def test_ros2_process_publishes_decodable_odometry_and_tokens(tmp_path, default_replica):
    from helpers_zenoh import REPO, child_env, router, wait_for, wait_for_heartbeat
    from transport.pubsub import Publisher
    from transport.session import open_session

    with router() as tcfg:
        cfg = {"transport": to_dict(tcfg) | {"stats_period_s": 0.2, "heartbeat_period_s": 0.2},
               "rig": {"calibration": str(default_replica)},
               "ros2": {"namespace": "/robot7", "domain_id": 3, "static_period_s": 0.3}}
        path = tmp_path / "system.yaml"
        path.write_text(yaml.safe_dump(cfg))
        proc = subprocess.Popen([sys.executable, "-m", "services.app.cli", "ros2", str(path)], cwd=REPO,
                                env=child_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        lines: list[str] = []
        threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")), daemon=True).start()
        try:
            with open_session(tcfg) as s:
                assert wait_for_heartbeat(s, tcfg, "ros2", 30.0, proc), "".join(lines)
                got: list = []
                key = f"3/robot7/odom/nav_msgs::msg::dds_::Odometry_/{JAZZY_ODOM_HASH}"
                sub = s.declare_subscriber(key, lambda smp: got.append((smp.payload.to_bytes(),
                                                                        smp.attachment.to_bytes())))
                static: list = []
                sub2 = s.declare_subscriber("3/robot7/tf_static/*/*", lambda smp: static.append(smp.payload.to_bytes()))
                pub = Publisher(s, f"{tcfg.namespace}/{topics.STATE.key}", m.EstimatorState, tcfg, block=True)
                assert pub.wait_for_subscribers(10.0)
                time.sleep(0.3)
                for i in range(40):
                    pub.publish(_state(i))
                    time.sleep(0.01)
                assert wait_for(lambda: len(got) >= 40, 10.0), (len(got), "".join(lines))
                ts = wire.type_store()
                for i, (payload, att) in enumerate(got[:40]):
                    o = ts.deserialize_cdr(payload, "nav_msgs/msg/Odometry")
                    np.testing.assert_allclose(_T_of(o.pose.pose), _pose(i), atol=1e-12)
                    a = wire.decode_attachment(att)
                    assert a.sequence_number == i + 1 and abs(a.source_timestamp_ns - time.time_ns()) < 60e9
                assert wait_for(lambda: len(static) > 0, 5.0)
                tfs = ts.deserialize_cdr(static[-1], "tf2_msgs/msg/TFMessage").transforms
                assert [t.child_frame_id for t in tfs] == ["imu", "cam0", "cam1"]
                tokens: list[str] = []

                def query() -> bool:  # a query can come back before the router has every token: ask again
                    tokens[:] = [str(r.ok.key_expr) for r in s.liveliness().get("@ros2_lv/3/**", timeout=2.0) if r.ok]
                    return len(tokens) >= 9  # the node and its 8 publishers
                assert wait_for(query, 10.0, 0.2), tokens
                kinds = {(t.split("/")[5], t.split("/")[9] if len(t.split("/")) > 9 else "") for t in tokens}
                assert ("NN", "") in kinds and ("MP", "%robot7%odom") in kinds and ("MP", "%robot7%tf") in kinds, tokens
                assert ("MP", "%robot7%map_mesh") in kinds and ("MP", "%robot7%tf_static") in kinds
                assert all(t.split("/")[8] == "sigmaslam" and t.split("/")[7] == "%robot7" for t in tokens)
                sub.undeclare()
                sub2.undeclare()
        finally:
            proc.terminate()
            proc.wait(timeout=20)
        assert proc.returncode == 0, "".join(lines)
