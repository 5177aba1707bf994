"""The compose stack under test: the compose command, its containers' state, and stopping it as Ctrl-C does."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
from dataclasses import dataclass
from pathlib import Path

PROJECT = "sigmaslam-smoke"


def compose_command() -> list[str] | None:
    """``docker compose`` (v2) where the plugin answers, else Debian's ``docker-compose`` (1.29); None if neither."""
    if os.environ.get("SIGMASLAM_COMPOSE"):
        return os.environ["SIGMASLAM_COMPOSE"].split()
    if shutil.which("docker") and subprocess.run(["docker", "compose", "version"], capture_output=True).returncode == 0:
        return ["docker", "compose"]
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    return None


@dataclass
class Container:
    """What ``docker inspect`` says of one container of the stack."""

    service: str
    id: str
    status: str          # created, running, exited, ...
    health: str          # starting, healthy, unhealthy, or '' without a health check
    exit_code: int
    restarts: int        # RestartCount: times the engine restarted it


def containers(project: str = PROJECT) -> dict[str, Container]:
    """The stack's containers by service (from the compose labels, so any compose version)."""
    ids = subprocess.run(["docker", "ps", "-aq", "--filter", f"label=com.docker.compose.project={project}"],
                         capture_output=True, text=True).stdout.split()
    if not ids:
        return {}
    r = subprocess.run(["docker", "inspect", *ids], capture_output=True, text=True)
    out = {}
    for c in json.loads(r.stdout or "[]"):
        service = c["Config"]["Labels"].get("com.docker.compose.service", c["Name"])
        state = c["State"]
        out[service] = Container(service, c["Id"][:12], state["Status"], (state.get("Health") or {}).get("Status", ""),
                                 int(state["ExitCode"]), int(c.get("RestartCount", 0)))
    return out


def logs(container_id: str) -> str:
    r = subprocess.run(["docker", "logs", container_id], capture_output=True, text=True, errors="replace")
    return r.stdout + r.stderr


class Stack:
    """``compose up`` of the given files as a child in its own process group, its output to ``log_path``."""

    def __init__(self, compose: list[str], files: list[Path], env: dict[str, str], cwd: Path, log_path: Path):
        self.base = [*compose, "-p", PROJECT, *(a for f in files for a in ("-f", str(f)))]
        self.env, self.cwd, self.log_path = {**os.environ, **env}, cwd, log_path
        self.proc: subprocess.Popen | None = None

    def run(self, *args: str, timeout_s: float = 300.0) -> subprocess.CompletedProcess:
        return subprocess.run([*self.base, *args], env=self.env, cwd=self.cwd, capture_output=True, text=True,
                              timeout=timeout_s)

    def up(self) -> None:
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen([*self.base, "up", "--no-build"], env=self.env, cwd=self.cwd, stdout=log,
                                         stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True)

    def exited(self) -> int | None:
        return None if self.proc is None else self.proc.poll()

    def interrupt(self, timeout_s: float) -> int | None:
        """Ctrl-C: SIGINT to compose's process group; its exit code, or None if it did not stop in time."""
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGINT)
        try:
            return self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            return None

    def down(self) -> None:
        """Remove what ``up`` made: containers, networks, volumes (images stay cached)."""
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()
        self.run("down", "--volumes", "--remove-orphans", "--timeout", "5", timeout_s=180)
