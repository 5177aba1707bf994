"""``sigmaslam odometry [CONFIG]``: the per-frame fast path (services/backend/odometry_node.py) as a process over
Zenoh, beside ``sigmaslam backend``.

frontend/frame + sensors/imu + estimator/window -> estimator/state (every frame). A frame waits up to
``backend.imu_wait_s`` for the IMU up to its time; a frame that cannot be tracked is dropped, counted and logged.
"""

from __future__ import annotations

import argparse
import logging

from services.backend.odometry_node import OdometryNode
from services.system_config import load_system_config
from shared.camera import CalibrationError
from shared.rig import load_rig_config
from transport.runner import run_node

log = logging.getLogger("sigmaslam.odometry")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", nargs="?", help="YAML system config (default: built-in defaults)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")


def main(args: argparse.Namespace) -> int:
    cfg = load_system_config(args.config, args.set)
    try:
        cameras = load_rig_config(cfg.rig)
    except (CalibrationError, FileNotFoundError) as exc:
        print(f"sigmaslam odometry: {exc}", flush=True)
        return 2
    node = OdometryNode(cfg, cameras)
    log.info("odometry: %d cameras", len(cameras))
    run_node(node, cfg.transport)
    return 0
