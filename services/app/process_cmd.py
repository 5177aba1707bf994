"""``sigmaslam <process> [CONFIG] [--set k=v]``: one process of the pipeline, from its description.

The one entry of every process command (``frontend``, ``backend``, ``depth``, ``mapping``, ``viewer``, ``player``,
``record``): it loads the system config (``CONFIG`` plus ``--set``), builds the process's node as its description
says (shared/process_description.py; a process that cannot start, e.g. a bad calibration or missing weights, exits
with its message before it joins the bus), warms it up, and runs it over Zenoh (transport.runner.run_node) until
SIGTERM/SIGINT; a process with a loop of its own (player, recorder) gets the config and its arguments.

Every process writes the stacks of all its threads to stderr on SIGUSR1 (``STACKS_SIGNAL``): the supervisor sends
it to a process that has not stopped in time after SIGTERM, just before SIGKILL, so its log says where it hung.
"""

from __future__ import annotations

import argparse
import faulthandler
import signal
import sys

from services.app.system_config import load_system_config
from shared.process_description import ProcessDescription, ProcessStartError, Start
from services.app.supervision import restart_count

STACKS_SIGNAL = signal.SIGUSR1  # dump every thread's stack to stderr (the supervisor's last word before SIGKILL)


def add_arguments(p: argparse.ArgumentParser, d: ProcessDescription) -> None:
    if d.arguments is not None:
        d.arguments(p)
    if d.config_positional:
        p.add_argument("config", nargs="?", help="YAML system config (default: built-in defaults)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")
    if d.output is not None:
        p.add_argument("--out", metavar="PATH", help=d.output.help)


def main(args: argparse.Namespace, d: ProcessDescription) -> int:
    faulthandler.register(STACKS_SIGNAL, all_threads=True)
    cfg = load_system_config(args.config, args.set)
    if d.main is not None:
        return int(d.main(cfg, args) or 0)
    from transport.runner import run_node

    try:
        node = d.build(cfg, Start(out_dir=getattr(args, "out", None), restarts=restart_count()))
        if d.warm_up is not None:
            d.warm_up(node)
    except ProcessStartError as exc:
        print(f"sigmaslam {d.cli_command}: {exc}", file=sys.stderr, flush=True)
        return exc.code
    ready = None if d.ready is None else (lambda: print(d.ready(node, cfg), flush=True))
    run_node(node, cfg.transport, ready=ready)
    return 0
