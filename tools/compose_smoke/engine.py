"""The Docker engine for the compose smoke test: the one that answers, or one started for the test and stopped after.

A started engine adds nothing to the machine's network: ``--bridge=none`` (no docker0 bridge), ``--iptables=false``
and ``--ip6tables=false`` (no NAT or filter rules). Containers then have host networking (docker/compose.host.yaml),
so all their traffic stays on the host's loopback. Starting one needs root and ``dockerd`` (Debian: docker.io).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

FLAGS = ("--bridge=none", "--iptables=false", "--ip6tables=false")


class EngineUnavailable(RuntimeError):
    """No engine answers and none can be started here (the smoke test skips, saying why)."""


def answers(timeout_s: float = 20.0) -> bool:
    """Whether ``docker info`` gets an answer from an engine."""
    if shutil.which("docker") is None:
        return False
    try:
        return subprocess.run(["docker", "info"], capture_output=True, timeout=timeout_s).returncode == 0
    except subprocess.TimeoutExpired:
        return False


class Engine:
    """``with Engine(log) as e:`` an engine that answers; ``e.started`` when this process started it."""

    def __init__(self, log_path: Path, start_timeout_s: float = 60.0):
        self.log_path = log_path
        self.start_timeout_s = start_timeout_s
        self.proc: subprocess.Popen | None = None

    @property
    def started(self) -> bool:
        return self.proc is not None

    def __enter__(self) -> Engine:
        return self.start()

    def start(self) -> Engine:
        """Make sure an engine answers: the running one, else one started here (EngineUnavailable if neither)."""
        if answers():
            return self
        if shutil.which("docker") is None:
            raise EngineUnavailable("no docker client (Debian package docker.io)")
        dockerd = shutil.which("dockerd") or ("/usr/sbin/dockerd" if Path("/usr/sbin/dockerd").exists() else None)
        if dockerd is None:
            raise EngineUnavailable("no engine answers and dockerd is not installed (Debian package docker.io)")
        if os.geteuid() != 0:
            raise EngineUnavailable("no engine answers, and starting dockerd needs root")
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        print(f"[compose-smoke] starting the engine: dockerd {' '.join(FLAGS)} (log {self.log_path})", flush=True)
        with open(self.log_path, "ab") as log:
            self.proc = subprocess.Popen([dockerd, *FLAGS], stdout=log, stderr=subprocess.STDOUT,
                                         stdin=subprocess.DEVNULL, start_new_session=True)
        deadline = time.monotonic() + self.start_timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                tail = self.log_path.read_text(errors="replace")[-1500:]
                rc, self.proc = self.proc.returncode, None
                raise EngineUnavailable(f"dockerd exited at start (exit code {rc}):\n{tail}")
            if answers(5.0):
                return self
            time.sleep(1.0)
        self.stop()
        raise EngineUnavailable(f"dockerd did not answer within {self.start_timeout_s:.0f} s (log {self.log_path})")

    def stop(self) -> None:
        """Stop the engine if this process started it (SIGTERM; it stops its containerd with it)."""
        if self.proc is None:
            return
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.proc = None

    def __exit__(self, *exc) -> None:
        self.stop()
