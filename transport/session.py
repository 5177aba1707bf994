"""Opening Zenoh sessions from :class:`TransportConfig`."""

from __future__ import annotations

import json
from pathlib import Path

import zenoh

from transport.config import TransportConfig


def zenoh_config(cfg: TransportConfig, role: str = "service") -> zenoh.Config:
    """Zenoh config for a service session (``role='service'``) or the router (``role='router'``)."""
    if cfg.zenoh_json5:
        path = Path(cfg.zenoh_json5)
        if not path.is_file():
            raise FileNotFoundError(f"transport.zenoh_json5: file not found: {path}")
        zc = zenoh.Config.from_file(str(path))
    else:
        zc = zenoh.Config()
    if role == "router":
        zc.insert_json5("mode", json.dumps("router"))
        zc.insert_json5("listen/endpoints", json.dumps(list(cfg.router_listen)))
        zc.insert_json5("connect/endpoints", json.dumps(list(cfg.router_connect)))
    else:
        zc.insert_json5("mode", json.dumps(cfg.mode))
        zc.insert_json5("connect/endpoints", json.dumps(list(cfg.connect)))
        if cfg.mode == "peer":
            zc.insert_json5("listen/endpoints", json.dumps(list(cfg.listen)))
    zc.insert_json5("scouting/multicast/enabled", json.dumps(cfg.multicast_scouting))
    zc.insert_json5("transport/shared_memory/enabled", json.dumps(cfg.shared_memory))
    zc.insert_json5("transport/link/tx/queue/congestion_control/drop/wait_before_drop",
                    json.dumps(max(1, int(round(cfg.drop_wait_ms * 1000)))))  # [us]
    # every sample carries its publisher's clock at put (transport.pubsub.sample_sent_ns): latencies from send times
    # do not depend on how soon a busy subscriber ran its callback
    zc.insert_json5("timestamping/enabled", json.dumps({"router": True, "peer": True, "client": True}))
    return zc


def open_session(cfg: TransportConfig, role: str = "service") -> zenoh.Session:
    """Open a session; use it as a context manager (``with open_session(cfg) as s:``)."""
    return zenoh.open(zenoh_config(cfg, role))


def free_local_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (for a private router of a run or a test)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
