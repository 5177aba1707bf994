"""Transport configuration: how a process joins the Zenoh network and how it queues data."""

from __future__ import annotations

import dataclasses
from typing import Literal

from shared.config import param


@dataclasses.dataclass(frozen=True)
class TransportConfig:
    """Zenoh session settings shared by every sigmaslam process.

    By default nothing listens beyond loopback: services are peers that connect to the router that
    ``sigmaslam up`` (or ``sigmaslam router``) opens on ``tcp/127.0.0.1:7447``, then learn about each
    other through gossip and talk directly. Multicast scouting is off.
    """

    namespace: str = param("sigmaslam/robot0", "key-expression prefix of every topic; one per robot")
    mode: Literal["peer", "client"] = param("peer", "Zenoh mode of service sessions")
    connect: tuple[str, ...] = param(("tcp/127.0.0.1:7447",), "endpoints to connect to (the router)")
    listen: tuple[str, ...] = param(("tcp/127.0.0.1:0",), "endpoints this session listens on (port 0: any free port)")
    router_listen: tuple[str, ...] = param(("tcp/127.0.0.1:7447",), "endpoints the router session listens on")
    router_connect: tuple[str, ...] = param((), "other routers this router links to (multi-host: each host's router connects to the hub's)")
    multicast_scouting: bool = param(False, "discover peers by UDP multicast (off: explicit endpoints only)")
    shared_memory: bool = param(True, "use Zenoh shared memory for large payloads between processes on one host")
    shm_threshold_bytes: int = param(65536, "payloads at least this large go through shared memory", "B")
    shm_pool_bytes: int = param(64 * 1024 * 1024, "size of each publisher process's shared-memory pool", "B")
    drop_wait_ms: float = param(1.0, "how long a sample of a topic that may drop (queue policy 'latest': frames, "
                                "depth, states) waits for room in Zenoh's transmission queue before Zenoh drops it, "
                                "uncounted (Zenoh's wait_before_drop; 1 ms is Zenoh's default)", "ms")
    zenoh_json5: str = param("", "optional Zenoh JSON5 config file whose settings are applied first (TLS, auth, ACL)")
    heartbeat_period_s: float = param(1.0, "period of each service's heartbeat", "s")
    stats_period_s: float = param(1.0, "period of each service's stats message", "s")

    def __post_init__(self) -> None:
        if not self.heartbeat_period_s > 0 or not self.stats_period_s > 0:
            raise ValueError(f"transport.heartbeat_period_s and stats_period_s must be positive, got "
                             f"{self.heartbeat_period_s}, {self.stats_period_s}")
        if self.shm_threshold_bytes < 0 or self.shm_pool_bytes < 0:
            raise ValueError("transport.shm_threshold_bytes and shm_pool_bytes must be >= 0")
