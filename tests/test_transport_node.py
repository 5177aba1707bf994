"""The service shell (Node), the router command and the transport benchmark, as real processes."""

import dataclasses
import json
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from helpers_zenoh import REPO, child_env, free_port, router, service_config, spawn_python, wait_for, wait_for_heartbeat
from shared import topics
from shared.messages import Header, ImuSample
from transport.node import Node
from transport.pubsub import Publisher, Subscriber
from transport.session import open_session

SERVICE_CHILD = r"""
import json, sys, time
from shared import topics
from transport.config import TransportConfig
from transport.node import Node
from transport.queues import Empty

cfg = TransportConfig(**json.loads(sys.argv[1]))
with Node("worker", cfg) as node:
    imu = node.subscriber(topics.IMU)
    work = node.timer("work", budget_ms=1.0)
    while not node.stopped:
        try:
            imu.get(timeout=0.05)
        except Empty:
            continue
        with work:
            time.sleep(0.003)
print("clean exit", flush=True)
"""


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_node_publishes_stats_and_heartbeat_and_stops_on_signal(sig):
    with router(heartbeat_period_s=0.1, stats_period_s=0.2) as cfg, open_session(cfg) as s:
        ns = cfg.namespace
        stats = Subscriber(s, f"{ns}/stats/*", topics.STATS.msg_type, "all", 100)
        beats = Subscriber(s, f"{ns}/heartbeat/*", topics.HEARTBEAT.msg_type, "all", 200)
        child = spawn_python(SERVICE_CHILD, json.dumps(dataclasses.asdict(cfg)))
        try:
            assert wait_for_heartbeat(s, cfg, "worker", 30.0, child), f"no heartbeat; exit code {child.poll()}"
            pub = Publisher(s, topics.IMU.key_expr(ns), ImuSample, cfg, block=True)
            assert pub.wait_for_subscribers(5)
            for i in range(10):
                pub.publish(ImuSample(header=Header(stamp_ns=i, seq=i), omega_S=np.zeros(3), acc_S=np.zeros(3)))
                time.sleep(0.01)

            def worked():
                msgs = stats.drain()
                return any(m.stage_count[0] == 10 and m.queue_received[0] == 10 for m in msgs if m.stage_names == ("work",))

            assert wait_for(worked, 5)
            child.send_signal(sig)
            t0 = time.monotonic()
            out, err = child.communicate(timeout=5)
            assert time.monotonic() - t0 < 3.0
        finally:
            if child.poll() is None:
                child.kill()
                child.communicate()
        assert child.returncode == 0, err
        assert "clean exit" in out
        hb = beats.drain()
        assert {m.service for m in hb} == {"worker"} and hb[-1].state == "stopping" and hb[-1].pid == child.pid
        assert "running" in {m.state for m in hb} and len(hb) >= 3
        seqs = [m.header.seq for m in hb]
        assert seqs == sorted(seqs)
        for x in (stats, beats, pub):
            x.close()


def test_node_in_process_api():
    with router() as cfg:
        with Node("svc", cfg, handle_signals=False) as node:
            assert node.timer("a", 5.0) is node.timer("a")
            with pytest.raises(ValueError, match="per-service"):
                node.publisher(topics.STATS)
            pub = node.publisher(topics.CONTROL)
            got = []
            node.subscriber(topics.CONTROL, handler=got.append)
            assert pub.wait_for_subscribers(5)
            pub.publish(topics.CONTROL.msg_type(header=Header(stamp_ns=1), target="*", command="pause"))
            assert wait_for(lambda: len(got) == 1, 5) and got[0].command == "pause"
            assert not node.wait(0.01)
            node.stop()
            assert node.stopped and node.wait(0.01)
        assert node.session is None
        node.close()  # twice is fine
    with pytest.raises(ValueError, match="service name"):
        Node("a/b")


def test_router_command_serves_peers_and_stops_on_sigterm():
    port = free_port()
    cmd = [sys.executable, "-m", "services.app.cli", "router", "--listen", f"tcp/127.0.0.1:{port}"]
    proc = subprocess.Popen(cmd, cwd=REPO, env=child_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert "listening on tcp/127.0.0.1:%d" % port in proc.stdout.readline()
        cfg = service_config(port)
        with open_session(cfg) as a, open_session(cfg) as b:
            got = []
            sub = Subscriber(b, cfg.namespace + "/x", ImuSample, handler=got.append)
            pub = Publisher(a, cfg.namespace + "/x", ImuSample, cfg)
            assert pub.wait_for_subscribers(5)
            pub.publish(ImuSample(header=Header(stamp_ns=5), omega_S=np.zeros(3), acc_S=np.zeros(3)))
            assert wait_for(lambda: len(got) == 1, 5)
            sub.close()
            pub.close()
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=5)
        assert proc.returncode == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def test_bench_transport_short_run_writes_json(tmp_path):
    out = tmp_path / "bench.json"
    cmd = [sys.executable, "-m", "tools", "bench", "transport", "--duration", "1", "--samples", "100",
           "--json", str(out)]
    res = subprocess.run(cmd, cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert "round trip 64B" in res.stdout and "one-way image shm" in res.stdout
    r = json.loads(out.read_text())
    assert {"rtt_64B", "rtt_imu", "frames", "targets", "pass"} <= set(r)
    assert r["rtt_64B"]["n"] == 100 and r["rtt_64B"]["p50_ms"] > 0
    names = [f["name"] for f in r["frames"]]
    assert names == ["image shm", "image plain", "depth shm"]
    for f in r["frames"]:
        assert {"p50_ms", "p90_ms", "p99_ms", "max_ms", "sent", "delivered", "drops", "payload_bytes"} <= set(f)
        assert f["sent"] == 30 and f["delivered"] + f["drops"] >= f["sent"]
    assert r["frames"][0]["payload_bytes"] > 786432 and r["frames"][0]["received_shm"] == r["frames"][0]["delivered"]
    assert r["frames"][1]["received_shm"] == 0


def test_node_refuses_topics_its_process_does_not_declare():
    """A service's transport Node with its declaration (services/<process>/node.py) subscribes and publishes only
    what the declaration lists (stats/ and heartbeat/ belong to every node)."""
    from services.player.node import PlayerNode
    from shared.dataflow import UndeclaredTopic

    with router() as cfg:
        with Node("player", cfg, handle_signals=False, declared=PlayerNode) as node:
            node.publisher(topics.FRAME)
            node.subscriber(topics.CONTROL)
            node.subscriber(topics.HEARTBEAT)
            with pytest.raises(UndeclaredTopic, match="subscribes to 'depth/stereo'"):
                node.subscriber(topics.DEPTH_STEREO)
            with pytest.raises(UndeclaredTopic, match="publishes 'estimator/state'"):
                node.publisher(topics.STATE)
