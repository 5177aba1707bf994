"""``sigmaslam health SERVICE [CONFIG]``: exit 0 when SERVICE is alive on the bus, 1 otherwise.

Used by container health checks and deployment scripts. For a pipeline service, alive means a
``heartbeat/<SERVICE>`` message in state 'running' (or 'starting') arrives under the configured
namespace within ``--timeout`` seconds. For ``router``, alive means a client session can open to
``transport.connect`` and sees a router there.

The check joins as a Zenoh *client* (through the router, no listening socket of its own), so it
works the same on one host, in a container and across hosts.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import threading

import zenoh

from services.app.system_config import load_system_config
from shared import topics
from shared.messages import Heartbeat
from transport.config import TransportConfig
from transport.pubsub import Subscriber
from transport.session import open_session

ALIVE_STATES = ("running", "starting")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("service", help="service name as it publishes heartbeat/<name> (e.g. frontend), or 'router'")
    p.add_argument("config", nargs="?", help="YAML system config (default: built-in defaults)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")
    p.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for a heartbeat [s]")
    p.add_argument("--quiet", action="store_true", help="print nothing on success")


def wait_for_heartbeat(cfg: TransportConfig, service: str, timeout_s: float) -> Heartbeat | None:
    """The first alive heartbeat of ``service`` seen within ``timeout_s`` seconds, or None."""
    seen: list[Heartbeat] = []
    got = threading.Event()

    def on_heartbeat(msg: Heartbeat) -> None:
        if msg.service == service and msg.state in ALIVE_STATES and not got.is_set():
            seen.append(msg)
            got.set()

    key = f"{cfg.namespace.rstrip('/')}/{topics.per_service(topics.HEARTBEAT, service)}"
    with open_session(cfg) as session:
        sub = Subscriber(session, key, Heartbeat, handler=on_heartbeat, name="health")
        try:
            got.wait(timeout_s)
        finally:
            sub.close()
    return seen[0] if seen else None


def router_reachable(cfg: TransportConfig) -> list[str]:
    """Ids of the routers a client session reaches at ``cfg.connect`` (empty if none)."""
    with open_session(cfg) as session:
        return [str(z) for z in session.info.routers_zid()]


def main(args: argparse.Namespace) -> int:
    if not args.service or "/" in args.service or "*" in args.service:
        print(f"sigmaslam health: bad service name {args.service!r}", file=sys.stderr)
        return 2
    if not args.timeout > 0:
        print("sigmaslam health: --timeout must be positive", file=sys.stderr)
        return 2
    cfg = dataclasses.replace(load_system_config(args.config, args.set).transport, mode="client")
    try:
        if args.service == "router":
            routers = router_reachable(cfg)
            if not routers:
                print(f"sigmaslam health: no router at {', '.join(cfg.connect)}", file=sys.stderr)
                return 1
            if not args.quiet:
                print(f"router {routers[0]} reachable at {', '.join(cfg.connect)}", flush=True)
            return 0
        hb = wait_for_heartbeat(cfg, args.service, args.timeout)
    except (zenoh.ZError, FileNotFoundError, ValueError) as exc:
        print(f"sigmaslam health {args.service}: cannot reach the bus at {', '.join(cfg.connect)}: {exc}",
              file=sys.stderr)
        return 1
    if hb is None:
        print(f"sigmaslam health: no heartbeat from {args.service!r} under {cfg.namespace} within {args.timeout:g} s",
              file=sys.stderr)
        return 1
    if not args.quiet:
        print(f"{args.service} alive (pid {hb.pid}, state {hb.state})", flush=True)
    return 0
