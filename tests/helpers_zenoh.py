"""Shared helpers for tests that use real Zenoh on loopback: free ports, an in-process router,
configs pointing at it, and child Python processes running in the repository root."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
import uuid
from pathlib import Path
from typing import Callable, Iterator

from transport.config import TransportConfig
from transport.session import free_local_port, open_session

REPO = Path(__file__).resolve().parents[1]


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


def spawn_python(code: str, *args: str, stdout=subprocess.PIPE) -> subprocess.Popen:
    """Start ``python -c code args...`` in the repository root (text-mode pipes)."""
    return subprocess.Popen([sys.executable, "-c", code, *args], cwd=REPO, env=child_env(),
                            stdout=stdout, stderr=subprocess.PIPE, text=True)


def wait_for(predicate: Callable[[], bool], timeout: float = 5.0, interval: float = 0.01) -> bool:
    """Poll ``predicate`` until it is true or ``timeout`` seconds passed; returns its last value."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(interval)
    return bool(predicate())
