"""Multi-host deployment in network namespaces: the router on one "host", services on others.

Needs root (``ip netns add``); skipped with the reason otherwise. Every namespace and veth pair has a
per-run name and is deleted on exit (tools/netns_lab.py).
"""

from __future__ import annotations

import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from services.recorder.mcap_reader import read_recording
from shared.messages import DepthFrame, EstimatorState
from tests.helpers_zenoh import REPO, child_env
from tools.netns_lab import NetnsLab, unavailable_reason

REASON = unavailable_reason()
# service tier: processes in network namespaces (tools.netns_lab starts them; tests/conftest.py cannot see that)
pytestmark = [pytest.mark.service,
              pytest.mark.skipif(REASON is not None, reason=f"multi-host test skipped: {REASON}")]

SIGMASLAM = [sys.executable, "-m", "services.app.cli"]

# A process built on the project's Node, standing in for the robot's estimator and the GPU host's
# depth service: publishes typed EstimatorState at 30 Hz and fused DepthFrames at 10 Hz until stopped.
TALKER = r"""
import sys, time, numpy as np
from shared import topics
from shared.messages import DepthFrame, EstimatorState, Header
from transport.config import TransportConfig
from transport.node import Node
cfg = TransportConfig(namespace=sys.argv[1], mode="client", connect=[sys.argv[2]], heartbeat_period_s=0.2)
depth = np.full((384, 512), 2.0, np.float32)
with Node("talker", cfg) as node:
    state_pub, depth_pub = node.publisher(topics.STATE), node.publisher(topics.DEPTH_FUSED)
    i = 0
    while not node.wait(1 / 30):
        h = Header(stamp_ns=time.time_ns(), seq=i, frame_id="W")
        T = np.eye(4); T[0, 3] = 0.01 * i
        state_pub.publish(EstimatorState(header=h, T_WS=T, v_W=np.zeros(3), gyro_bias=np.zeros(3),
                                         acc_bias=np.zeros(3), covariance=np.eye(15)))
        if i % 3 == 0:
            depth_pub.publish(DepthFrame(header=h, depth=depth, sigma=depth * 0.1, K=np.eye(3), T_WC=T, source="fused"))
        i += 1
"""


def _popen(lab: NetnsLab, ns: str, argv: list[str]) -> subprocess.Popen:
    return lab.popen(ns, argv, cwd=REPO, env=child_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_output(proc: subprocess.Popen, needle: str, timeout: float = 20.0) -> str:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if needle in line:
            return line
        if not line and proc.poll() is not None:
            break
    pytest.fail(f"process did not print {needle!r} (rc {proc.poll()})")


def _health(lab: NetnsLab, ns: str, service: str, *sets: str, timeout: float = 8.0) -> subprocess.CompletedProcess:
    argv = [*SIGMASLAM, "health", service, "--timeout", str(timeout)]
    for s in sets:
        argv += ["--set", s]
    return subprocess.run(["ip", "netns", "exec", ns, *argv], cwd=REPO, env=child_env(), capture_output=True,
                          text=True, timeout=timeout + 30)


def test_typed_messages_cross_hosts_through_the_router(tmp_path: Path) -> None:
    namespace = f"sigmaslam/netns-{uuid.uuid4().hex[:6]}"
    out = tmp_path / "base.mcap"
    with NetnsLab(("robot", "base")) as lab:
        names = lab.exists()
        assert len(names) == 3
        router = _popen(lab, lab.router_ns, [*SIGMASLAM, "router", "--listen", "tcp/0.0.0.0:7447"])
        _wait_output(router, "listening")
        talker = _popen(lab, lab.ns["robot"], [sys.executable, "-c", TALKER, namespace, lab.endpoint("robot")])
        base_sets = [f"transport.namespace={namespace}", "transport.mode=client",
                     f"transport.connect=[{lab.endpoint('base')}]"]
        recorder = _popen(lab, lab.ns["base"], [*SIGMASLAM, "record", "--out", str(out),
                                                *[a for s in base_sets for a in ("--set", s)]])
        _wait_output(recorder, "recording")
        # health checks across the boundary, each way: the real CLI in the other namespace
        h = _health(lab, lab.ns["robot"], "recorder", f"transport.namespace={namespace}",
                    f"transport.connect=[{lab.endpoint('robot')}]")
        assert h.returncode == 0, h.stderr
        h = _health(lab, lab.ns["base"], "talker", *base_sets)
        assert h.returncode == 0, h.stderr
        time.sleep(1.5)
        recorder.terminate()
        assert recorder.wait(15) == 0, recorder.stderr.read()[-2000:]
        assert talker.poll() is None, talker.stderr.read()[-2000:]
    assert lab.exists() == [], "lab namespaces left behind"

    states = [m for k, _t, m in read_recording(out) if k == f"{namespace}/estimator/state"]
    depths = [m for k, _t, m in read_recording(out) if k == f"{namespace}/depth/fused"]
    assert len(states) >= 20 and all(isinstance(m, EstimatorState) for m in states)
    assert len(depths) >= 5 and all(isinstance(m, DepthFrame) for m in depths)
    assert depths[0].depth.shape == (384, 512) and float(depths[0].depth[0, 0]) == 2.0
    seqs = [m.header.seq for m in states]
    assert seqs == sorted(seqs)
    assert states[-1].T_WS[0, 3] == pytest.approx(0.01 * seqs[-1])


def test_default_router_listens_on_loopback_only() -> None:
    """A router with the built-in defaults is reachable inside its own host, not from another host."""
    with NetnsLab(("other",)) as lab:
        router = _popen(lab, lab.router_ns, [*SIGMASLAM, "router"])
        _wait_output(router, "listening")
        inside = _health(lab, lab.router_ns, "router")
        assert inside.returncode == 0, inside.stderr
        outside = _health(lab, lab.ns["other"], "router", f"transport.connect=[{lab.endpoint('other')}]")
        assert outside.returncode == 1
        assert "cannot reach" in outside.stderr


def test_lab_cleans_up_after_an_error() -> None:
    lab = NetnsLab(("x",))
    with pytest.raises(RuntimeError, match="boom"):
        with lab:
            assert len(lab.exists()) == 2
            raise RuntimeError("boom")
    assert lab.exists() == []


def test_multihost_configs_router_per_host(tmp_path: Path) -> None:
    """configs/multihost as shipped: a router per host linked to the hub's; 'hub' resolves to the hub host."""
    out = tmp_path / "hub.mcap"
    hub, robot, gpu = (f"configs/multihost/{h}.yaml" for h in ("hub", "robot", "gpu"))
    with NetnsLab(("robot", "gpu")) as lab:
        hub_router = _popen(lab, lab.router_ns, [*SIGMASLAM, "router", hub])
        _wait_output(hub_router, "listening")
        for host, cfg in (("robot", robot), ("gpu", gpu)):
            _wait_output(_popen(lab, lab.ns[host], [*SIGMASLAM, "router", cfg]), "listening")
        # the robot's router listens on its loopback only: not reachable from the hub host
        assert _health(lab, lab.router_ns, "router", f"transport.connect=[tcp/{lab.host_ip('robot')}:7447]",
                       timeout=3).returncode == 1
        talker = _popen(lab, lab.ns["robot"], [sys.executable, "-c", TALKER, "sigmaslam/robot0", "tcp/127.0.0.1:7447"])
        recorder = _popen(lab, lab.router_ns, [*SIGMASLAM, "record", hub, "--out", str(out)])
        _wait_output(recorder, "recording")
        h = subprocess.run(["ip", "netns", "exec", lab.ns["gpu"], *SIGMASLAM, "health", "talker", gpu, "--timeout", "8"],
                           cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=60)
        assert h.returncode == 0, h.stderr  # robot -> robot router -> hub -> gpu router -> gpu
        h = subprocess.run(["ip", "netns", "exec", lab.ns["robot"], *SIGMASLAM, "health", "recorder", robot,
                            "--timeout", "8"], cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=60)
        assert h.returncode == 0, h.stderr
        time.sleep(1.0)
        recorder.terminate()
        assert recorder.wait(15) == 0
        assert talker.poll() is None
    states = [m for k, _t, m in read_recording(out) if k == "sigmaslam/robot0/estimator/state"]
    depths = [m for k, _t, m in read_recording(out) if k == "sigmaslam/robot0/depth/fused"]
    assert len(states) >= 15 and isinstance(states[0], EstimatorState)
    assert len(depths) >= 4 and depths[-1].depth.shape == (384, 512)


def test_bench_netns_delivers_every_message_in_each_layout() -> None:
    import argparse

    from tools.bench_netns import benchmark, format_table

    result = benchmark(argparse.Namespace(duration=0.5, skip_peer=True))
    cases = {(r["case"], r["payload"]) for r in result["rows"]}
    assert cases == {(c, p) for c in ("host client", "netns client", "netns 3 routers") for p in ("state", "depth")}
    for r in result["rows"]:
        assert r["sent"] > 0 and r["delivered"] == r["sent"], r
        assert 0 < r["p50_ms"] < 1000.0
    assert "netns 3 routers" in format_table(result)


def test_compose_commands_run_as_written(tmp_path: Path) -> None:
    """The router, recorder and their health checks from docker/compose.yaml, argv as written, each in
    its own namespace where 'router' resolves to the router's, like containers on the compose network."""
    import yaml

    services = yaml.safe_load((REPO / "docker" / "compose.yaml").read_text())["services"]

    def argv(service: str, key: str) -> list[str]:
        cmd = services[service]["healthcheck"]["test"][1:] if key == "health" else services[service]["command"]
        assert cmd[0] == "sigmaslam"
        return [*SIGMASLAM, *cmd[1:]]

    with NetnsLab(("recorder", "probe")) as lab:
        _wait_output(_popen(lab, lab.router_ns, argv("router", "command")), "listening")
        probe = lab.run(lab.ns["probe"], argv("router", "health"))
        assert probe.returncode == 0, probe.stderr
        # the recorder's container path /recordings is replaced by a temporary file
        recorder = _popen(lab, lab.ns["recorder"], [*argv("recorder", "command"), "--out", str(tmp_path / "r.mcap")])
        _wait_output(recorder, "recording")
        probe = lab.run(lab.ns["probe"], argv("recorder", "health"))
        assert probe.returncode == 0, probe.stderr
        probe = lab.run(lab.ns["probe"], [*argv("frontend", "health"), "--timeout", "1"])
        assert probe.returncode == 1, "no frontend is running"
