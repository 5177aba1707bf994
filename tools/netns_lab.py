"""A throw-away multi-host network made of Linux network namespaces (needs root and ``ip``).

One namespace plays the router host; every other "host" namespace is linked to it by its own veth
pair on its own /24 subnet, so hosts reach each other only through the router host, like machines
on separate links::

    with NetnsLab(("robot", "gpu")) as lab:
        router = lab.popen(lab.router_ns, ["sigmaslam", "router", "--listen", "tcp/0.0.0.0:7447"])
        robot = lab.popen(lab.ns["robot"], [...,"--set", f"transport.connect=[{lab.endpoint('robot')}]"])

Nothing is created in the host's own namespace: every interface lives inside a lab namespace, and
deleting the namespaces (always done on exit, also after errors) removes the veth pairs with them.
Names carry a random per-lab suffix so that concurrent labs do not collide.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import uuid
from pathlib import Path
from typing import Sequence

ROUTER_PORT = 7447


def unavailable_reason() -> str | None:
    """Why network namespaces cannot be used here, or None if they can."""
    if os.name != "posix" or not hasattr(os, "geteuid"):
        return "network namespaces need Linux"
    if os.geteuid() != 0:
        return "network namespaces need root (ip netns add)"
    if shutil.which("ip") is None:
        return "the 'ip' command (iproute2) is not installed"
    probe = f"sstest{uuid.uuid4().hex[:6]}"
    r = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if r.returncode != 0:
        return f"'ip netns add' failed: {r.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return None


class NetnsLab:
    """Router namespace plus one namespace per host, each host linked to the router by a veth pair."""

    def __init__(self, hosts: Sequence[str] = ("a", "b"), router_names: Sequence[str] = ("hub", "router")) -> None:
        """``router_names``: host names that resolve to the router host inside every host namespace
        (through ``/etc/netns/<ns>/hosts``, which ``ip netns exec`` mounts over /etc/hosts)."""
        if not hosts or len(set(hosts)) != len(hosts):
            raise ValueError(f"hosts must be distinct names, got {hosts!r}")
        tag = uuid.uuid4().hex[:6]
        self.tag = tag
        self.router_ns = f"ss{tag}r"
        self.ns = {h: f"ss{tag}h{i}" for i, h in enumerate(hosts)}
        self._links = {h: (f"ss{tag}r{i}", f"ss{tag}h{i}", f"10.77.{i + 1}.1", f"10.77.{i + 1}.2")
                       for i, h in enumerate(hosts)}
        self.router_names = tuple(router_names)
        self._created: list[str] = []
        self._procs: list[subprocess.Popen] = []

    # addresses -------------------------------------------------------------------------------

    def router_ip(self, host: str) -> str:
        """The router host's address on ``host``'s link."""
        return self._links[host][2]

    def host_ip(self, host: str) -> str:
        return self._links[host][3]

    def endpoint(self, host: str, port: int = ROUTER_PORT, proto: str = "tcp") -> str:
        """Zenoh endpoint of the router as seen from ``host``."""
        return f"{proto}/{self.router_ip(host)}:{port}"

    # lifecycle -------------------------------------------------------------------------------

    def __enter__(self) -> NetnsLab:
        try:
            self._setup()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _ip(self, *args: str) -> None:
        r = subprocess.run(["ip", *args], capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"ip {' '.join(args)}: {r.stderr.strip()}")

    def _add_ns(self, name: str) -> None:
        self._ip("netns", "add", name)
        self._created.append(name)
        self._ip("-n", name, "link", "set", "lo", "up")

    def _setup(self) -> None:
        self._add_ns(self.router_ns)
        for host, ns in self.ns.items():
            self._add_ns(ns)
            r_if, h_if, r_ip, h_ip = self._links[host]
            # create the pair inside the router namespace, then move one end: nothing touches the host's namespace
            self._ip("-n", self.router_ns, "link", "add", r_if, "type", "veth", "peer", "name", h_if)
            self._ip("-n", self.router_ns, "link", "set", h_if, "netns", ns)
            self._ip("-n", self.router_ns, "addr", "add", f"{r_ip}/24", "dev", r_if)
            self._ip("-n", ns, "addr", "add", f"{h_ip}/24", "dev", h_if)
            self._ip("-n", self.router_ns, "link", "set", r_if, "up")
            self._ip("-n", ns, "link", "set", h_if, "up")
            if self.router_names:
                etc = Path("/etc/netns") / ns
                etc.mkdir(parents=True, exist_ok=True)
                (etc / "hosts").write_text(f"127.0.0.1 localhost\n{r_ip} {' '.join(self.router_names)}\n")

    def popen(self, ns: str, argv: Sequence[str], **kwargs: object) -> subprocess.Popen:
        """Start ``argv`` inside namespace ``ns`` (``ip netns exec`` execs it: the pid is the command's).
        Processes still running at close are terminated, then killed."""
        if ns not in self._created:
            raise ValueError(f"{ns!r} is not a namespace of this lab")
        proc = subprocess.Popen(["ip", "netns", "exec", ns, *argv], **kwargs)
        self._procs.append(proc)
        return proc

    def run(self, ns: str, argv: Sequence[str], timeout: float = 30.0) -> subprocess.CompletedProcess:
        if ns not in self._created:
            raise ValueError(f"{ns!r} is not a namespace of this lab")
        return subprocess.run(["ip", "netns", "exec", ns, *argv], capture_output=True, text=True, timeout=timeout)

    def close(self) -> None:
        for proc in self._procs:
            if proc.poll() is None:
                proc.terminate()
        for proc in self._procs:
            try:
                proc.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        self._procs.clear()
        for name in reversed(self._created):
            subprocess.run(["ip", "netns", "del", name], capture_output=True)
            shutil.rmtree(Path("/etc/netns") / name, ignore_errors=True)
        self._created.clear()

    def exists(self) -> list[str]:
        """Lab namespaces that still exist (for tests of the cleanup)."""
        out = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
        names = {line.split()[0] for line in out.splitlines() if line.strip()}
        return sorted(n for n in [self.router_ns, *self.ns.values()] if n in names)
