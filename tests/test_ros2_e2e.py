"""sigmaslam live on ROS 2 end to end (issue 58), on the real EuRoC frames: a ROS 2 network of its own (a Zenoh router
standing for the robot's rmw_zenohd), the player as the stand-in robot on it, ``sigmaslam ros2_input`` reading the
robot's topics, the pipeline, and the ROS 2 face publishing back; an independent Zenoh subscriber on that network
decodes the Odometry on the key a ROS 2 subscriber uses, and a liveliness query finds the three ROS 2 nodes."""

from __future__ import annotations

import json
import subprocess
import sys
import threading

import numpy as np
import pytest

from shared import ros2_wire as wire

pytestmark = pytest.mark.e2e


def test_run_on_ros2_input_with_the_face_on(tmp_path, real_data):
    from helpers_zenoh import REPO, child_env, router
    from shared.euroc import read_trajectory
    from transport.session import open_session

    micro = real_data("euroc_V1_01_micro")
    key = f"0/robot0/odom/{wire.dds_type_name('nav_msgs/msg/Odometry')}/{wire.type_hash('nav_msgs/msg/Odometry')}"
    with router() as ros_net, open_session(ros_net) as s:
        got: list[bytes] = []
        sub = s.declare_subscriber(key, lambda smp: got.append(smp.payload.to_bytes()))
        tokens: list[str] = []
        live = s.liveliness().declare_subscriber("@ros2_lv/0/**", lambda smp: tokens.append(str(smp.key_expr)))
        services = "supervisor.services=[{name: frontend, argv: [frontend]}, {name: backend, argv: [backend]}]"
        out = tmp_path / "run"
        proc = subprocess.Popen(
            [sys.executable, "-m", "services.app.cli", "run", str(micro), "--out", str(out), "--ros2-input",
             "--gt", str(micro / "groundtruth_tum.txt"), "--set", services, "--set", "ros2.enabled=true",
             "--set", f"ros2.connect=[{ros_net.connect[0]}]", "--set", "ros2.namespace=/robot0",
             "--timeout-s", "400"], cwd=REPO, env=child_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            text=True)
        lines: list[str] = []
        reader = threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")), daemon=True)
        reader.start()
        assert proc.wait(timeout=600) == 0, "".join(lines)[-4000:]
        reader.join(5)
        sub.undeclare()
        live.undeclare()
    log = "".join(lines)
    stats = json.loads((out / "stats.json").read_text())
    ate = json.loads((out / "ate.json").read_text())
    # every frame the robot sent went through ros2_input and got a state, as with the player
    assert "ros2_input: 60 frames" in log and "dropped: none" in log, log[-3000:]
    assert stats["frames_sent"] == 60 and ate["ate_rmse_m"] < 0.02, (stats, ate)
    # the face: the causal poses decoded from the ROS 2 key by rosbags (>= 95 % of them), equal to the run's
    causal = read_trajectory(out / "trajectory_causal.txt")
    ts = wire.type_store()
    odom = [ts.deserialize_cdr(b, "nav_msgs/msg/Odometry") for b in got]
    assert len(odom) >= 0.95 * len(causal.stamps_ns), (len(odom), len(causal.stamps_ns))
    by_stamp = {o.header.stamp.sec * 10**9 + o.header.stamp.nanosec: o for o in odom}
    for t, p in zip(causal.stamps_ns, causal.p_WS):
        if int(t) in by_stamp:
            q = by_stamp[int(t)].pose.pose.position
            np.testing.assert_allclose([q.x, q.y, q.z], p, atol=1e-6)
    # discovery: the face, the input and the robot as ROS 2 nodes with their publishers and subscriptions
    nodes = {t.split("/")[8] for t in tokens if t.split("/")[5] == "NN"}
    assert {"sigmaslam", "sigmaslam_input", "robot"} <= nodes, tokens
    kinds = {(t.split("/")[5], t.split("/")[9]) for t in tokens if len(t.split("/")) > 9}
    assert {("MP", "%robot0%odom"), ("MP", "%robot0%tf"), ("MS", "%cam0%image_raw"), ("MP", "%cam0%image_raw"),
            ("MS", "%imu0")} <= kinds, kinds
