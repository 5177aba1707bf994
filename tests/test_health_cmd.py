"""sigmaslam health: exit codes and messages against a real router and a real Node process on loopback."""

from __future__ import annotations

import subprocess
import sys

from tests.helpers_zenoh import REPO, child_env, free_port, router, spawn_python, wait_for_heartbeat
from transport.session import open_session

NODE = r"""
import sys, time
from transport.config import TransportConfig
from transport.node import Node
cfg = TransportConfig(namespace=sys.argv[1], connect=[sys.argv[2]], heartbeat_period_s=0.2)
with Node("tracker", cfg) as node:
    node.wait(30)
"""


def health(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "services.app.cli", "health", *args], cwd=REPO, env=child_env(),
                          capture_output=True, text=True, timeout=60)


def _sets(cfg) -> list[str]:
    return ["--set", f"transport.namespace={cfg.namespace}", "--set", f"transport.connect=[{cfg.connect[0]}]"]


def test_no_router() -> None:
    r = health("router", "--set", f"transport.connect=[tcp/127.0.0.1:{free_port()}]")
    assert r.returncode == 1 and "cannot reach the bus" in r.stderr


def test_router_and_service_heartbeat() -> None:
    with router() as cfg:
        assert health("router", *_sets(cfg)).returncode == 0
        r = health("tracker", *_sets(cfg), "--timeout", "1")
        assert r.returncode == 1 and "no heartbeat from 'tracker'" in r.stderr
        node = spawn_python(NODE, cfg.namespace, cfg.connect[0])
        try:
            with open_session(cfg) as session:  # the node is up (its start can take seconds on a loaded machine)
                assert wait_for_heartbeat(session, cfg, "tracker", 30.0, node), f"no heartbeat; exit code {node.poll()}"
            r = health("tracker", *_sets(cfg), "--timeout", "5")
            assert r.returncode == 0, r.stderr
            assert "tracker alive" in r.stdout
            # another namespace (another robot) does not count
            other = ["--set", "transport.namespace=sigmaslam/other", "--set", f"transport.connect=[{cfg.connect[0]}]"]
            assert health("tracker", *other, "--timeout", "1").returncode == 1
        finally:
            node.terminate()
            node.wait(10)


def test_bad_input_gives_clear_errors() -> None:
    r = health("a/b")
    assert r.returncode == 2 and "bad service name" in r.stderr
    r = health("frontend", "--timeout", "0")
    assert r.returncode == 2 and "--timeout" in r.stderr
    r = health("frontend", "--set", "transport.no_such_key=1")
    assert r.returncode == 2 and "config error" in r.stderr
