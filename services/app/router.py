"""``sigmaslam router``: the Zenoh router that services connect to; runs until SIGTERM/SIGINT."""

from __future__ import annotations

import argparse
import dataclasses
import logging
import signal
import sys
import threading

import zenoh

from services.app.system_config import load_system_config
from transport.session import open_session

log = logging.getLogger("sigmaslam.router")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", nargs="?", help="YAML system config (default: built-in defaults)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable; replaces transport.router_listen)")


def main(args: argparse.Namespace) -> int:
    cfg = load_system_config(args.config, args.set).transport
    if args.listen:
        cfg = dataclasses.replace(cfg, router_listen=tuple(args.listen))
    stop = threading.Event()

    def on_signal(signum: int, _frame: object) -> None:
        log.info("%s received, closing the router", signal.Signals(signum).name)
        stop.set()

    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, on_signal)
    try:
        session = open_session(cfg, role="router")
    except zenoh.ZError as exc:
        print(f"sigmaslam router: cannot open the router on {cfg.router_listen}: {exc}", file=sys.stderr)
        return 1
    with session:
        log.info("router %s listening on %s (shared memory %s)", session.zid(), ", ".join(cfg.router_listen),
                 "on" if cfg.shared_memory else "off")
        print(f"sigmaslam router listening on {' '.join(cfg.router_listen)}", flush=True)
        while not stop.wait(0.5):
            pass
    return 0
