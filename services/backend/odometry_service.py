"""``sigmaslam odometry [CONFIG]``: the per-frame fast path (services/backend/odometry_node.py) as a process over
Zenoh, beside ``sigmaslam backend``.

frontend/frame + sensors/imu + estimator/window -> estimator/state (every frame). A frame waits up to
``backend.imu_wait_s`` for the IMU up to its time; a frame that cannot be tracked is dropped, counted and logged.
"""

from __future__ import annotations

import logging

from services.backend.odometry_node import OdometryNode
from services.backend.service import add_arguments  # noqa: F401 (the same command line as sigmaslam backend)
from services.system_config import service_config_and_rig
from transport.runner import run_node

log = logging.getLogger("sigmaslam.odometry")


def main(args) -> int:
    started = service_config_and_rig(args, "odometry")
    if started is None:
        return 2
    cfg, cameras = started
    log.info("odometry: %d cameras", len(cameras))
    run_node(OdometryNode(cfg, cameras), cfg.transport)
    return 0
