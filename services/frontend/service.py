"""``sigmaslam frontend [CONFIG]``: the frontend node (services/frontend/node.py) as a process over Zenoh.

sensors/frame (+ sensors/imu gyro, estimator/state gyro bias) -> frontend/frame, frontend/keyframe_features.
"""

from __future__ import annotations

import argparse
import logging

from services.frontend.node import FrontendNode
from shared.supervision import restart_count
from services.system_config import load_system_config
from shared.camera import CalibrationError
from shared.rig import load_rig_config
from transport.runner import run_node

log = logging.getLogger("sigmaslam.frontend")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", nargs="?", help="YAML system config (default: built-in defaults)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")


def main(args: argparse.Namespace) -> int:
    cfg = load_system_config(args.config, args.set)
    try:
        cameras = load_rig_config(cfg.rig)
    except (CalibrationError, FileNotFoundError) as exc:
        print(f"sigmaslam frontend: {exc}", flush=True)
        return 2
    # after a supervisor restart, landmark ids continue in a range of their own (2^40 ids per life)
    node = FrontendNode(cfg.frontend, cameras, first_landmark_id=restart_count() << 40)
    log.info("frontend: %d cameras %s", len(cameras), node.names)
    run_node(node, cfg.transport)
    return 0
