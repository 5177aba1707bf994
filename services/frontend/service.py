"""``sigmaslam frontend [CONFIG]``: the frontend node (services/frontend/node.py: tracking and the per-frame fast
path) over Zenoh.

sensors/frame + sensors/imu + estimator/window -> estimator/state (every frame), frontend/frame,
frontend/keyframe_features.
"""

from __future__ import annotations

import argparse
import logging

from services.frontend.node import make_node
from shared.supervision import restart_count
from services.system_config import service_config_and_rig
from transport.runner import run_node

log = logging.getLogger("sigmaslam.frontend")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", nargs="?", help="YAML system config (default: built-in defaults)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")


def main(args: argparse.Namespace) -> int:
    started = service_config_and_rig(args, "frontend")
    if started is None:
        return 2
    cfg, cameras = started
    # after a supervisor restart, landmark ids continue in a range of their own (2^40 ids per life)
    node = make_node(cfg, cameras, first_landmark_id=restart_count() << 40)
    log.info("frontend: %d cameras %s", len(cameras), node.names)
    run_node(node, cfg.transport)
    return 0
