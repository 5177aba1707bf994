"""Shared helpers for tests that use real Zenoh on loopback: free ports, an in-process router,
configs pointing at it, and child Python processes running in the repository root."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import threading
import time
import uuid
from typing import Callable, Iterator

from shared import topics
from shared.paths import REPO_ROOT
from shared.messages import Heartbeat
from transport.config import TransportConfig
from transport.pubsub import Subscriber
from transport.session import free_local_port, open_session

REPO = REPO_ROOT  # the repository root (children run there)


free_port = free_local_port  # the one helper; tests import it under this name


def service_config(port: int, **overrides: object) -> TransportConfig:
    """Service config connecting to a router on ``port``, with a namespace unique to this call."""
    fields = dict(namespace=f"sigmaslam/test-{uuid.uuid4().hex[:8]}", connect=[f"tcp/127.0.0.1:{port}"],
                  router_listen=[f"tcp/127.0.0.1:{port}"], listen=["tcp/127.0.0.1:0"])
    fields.update(overrides)
    return TransportConfig(**fields)


@contextlib.contextmanager
def router(port: int | None = None, **overrides: object) -> Iterator[TransportConfig]:
    """Run a Zenoh router in this process on a free port; yields the service config for it."""
    port = port or free_port()
    cfg = service_config(port, **overrides)
    with open_session(cfg, role="router"):
        yield cfg


def child_env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def spawn_python(code: str, *args: str, stdout=subprocess.PIPE, stdin=None) -> subprocess.Popen:
    """Start ``python -c code args...`` in the repository root (text-mode pipes)."""
    return subprocess.Popen([sys.executable, "-c", code, *args], cwd=REPO, env=child_env(),
                            stdin=stdin, stdout=stdout, stderr=subprocess.PIPE, text=True)


def wait_for(predicate: Callable[[], bool], timeout: float = 5.0, interval: float = 0.01) -> bool:
    """Poll ``predicate`` until it is true or ``timeout`` seconds passed; returns its last value."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(interval)
    return bool(predicate())


def wait_for_heartbeat(session, cfg: TransportConfig, service: str, timeout: float = 30.0,
                       proc: subprocess.Popen | None = None) -> bool:
    """Wait until ``service`` (a Node in a child process) publishes a periodic 'running' heartbeat (seq >= 1: its
    subscriptions are declared by then; the rule of the player's ``--wait-for``) on ``cfg``'s namespace, through
    ``session``. False after ``timeout`` seconds or as soon as ``proc`` (if given) has exited."""
    up = threading.Event()

    def on_heartbeat(msg: Heartbeat) -> None:
        if msg.state == "running" and msg.header.seq >= 1:
            up.set()

    key = f"{cfg.namespace.rstrip('/')}/{topics.per_service(topics.HEARTBEAT, service)}"
    sub = Subscriber(session, key, Heartbeat, handler=on_heartbeat, name=f"test-wait-{service}")
    try:
        wait_for(lambda: up.is_set() or (proc is not None and proc.poll() is not None), timeout)
    finally:
        sub.close()
    return up.is_set()
