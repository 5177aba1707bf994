"""``sigmaslam up [CONFIG]``: run the router and every enabled service of ``supervisor.services``.

The resolved config (file plus ``--set`` overrides) is written to
``<supervisor.run_dir>/<UTC time>-<pid>/config.yaml`` and passed to each child as its CONFIG
argument (see :mod:`services.app.supervisor`). Stop with Ctrl-C or SIGTERM.
"""

from __future__ import annotations

import argparse
import os
import signal
import time
from pathlib import Path

from services.app import processes
from services.app.cli import command_names
from services.app.supervisor import Supervisor, validate
from services.app.system_config import load_system_config
from shared.config import override, to_yaml


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", nargs="?", help="YAML system config (e.g. configs/default.yaml; default: built-in defaults)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")
    p.add_argument("--ros2-input", action="store_true", help="read the robot's camera and IMU topics over ROS 2 "
                   "(sigmaslam ros2_input, topics in ros2.input; = --set ros2.input.enabled=true)")
    p.add_argument("--run-dir", metavar="DIR", help="folder of this run (default: <supervisor.run_dir>/<UTC>-<pid>)")


def main(args: argparse.Namespace) -> int:
    cfg = load_system_config(args.config, [*args.set, *(["ros2.input.enabled=true"] if args.ros2_input else [])])
    extra = processes.switched_on(cfg, cfg.supervisor.services)  # e.g. ros2.enabled: the ROS 2 face
    if extra:
        cfg = override(cfg, {"supervisor.services": [*cfg.supervisor.services, *extra]})
    validate(cfg.supervisor, command_names())
    run_dir = Path(args.run_dir) if args.run_dir else (
        Path(cfg.supervisor.run_dir) / f"{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}-{os.getpid()}")
    run_dir.mkdir(parents=True, exist_ok=True)
    config_path = (run_dir / "config.yaml").resolve()
    config_path.write_text(to_yaml(cfg))
    sup = Supervisor(cfg.supervisor, config_path, run_dir.resolve())
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, sup.request_stop)
    print(f"[sigmaslam up] run folder {run_dir}, config {config_path}", flush=True)
    return sup.run()
