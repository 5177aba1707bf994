"""``sigmaslam backend [CONFIG]``: the back-end node (services/backend/node.py) as a process over Zenoh.

sensors/imu + frontend/frame (+ frontend/keyframe_features, estimator/state, map/field, map/o2p_points,
depth/stereo, sensors/end) -> estimator/window, estimator/keyframes, estimator/landmarks,
estimator/trajectory_final; the fast path in ``sigmaslam frontend`` publishes estimator/state from its windows. A feature
frame waits up to ``backend.imu_wait_s`` for the IMU samples up to its time; a frame the estimator refuses (bad
arrays, time going backwards, IMU gap) is dropped, counted and logged, never fatal.
"""

from __future__ import annotations

import argparse
import logging
import time

from services.backend.node import make_node
from shared.occupancy.query import warm_up as warm_up_queries
from shared.supervision import restart_count
from services.system_config import service_config_and_rig
from transport.runner import run_node

log = logging.getLogger("sigmaslam.backend")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", nargs="?", help="YAML system config (default: built-in defaults)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")


def main(args: argparse.Namespace) -> int:
    started = service_config_and_rig(args, "backend")
    if started is None:
        return 2
    cfg, cameras = started
    node = make_node(cfg, cameras, restarted=restart_count() > 0)
    if cfg.o2p.enabled:  # before the first heartbeat: a player waiting for the back end starts after this
        t0 = time.monotonic()
        warm_up_queries()
        log.info("backend: occupancy queries loaded in %.2f s", time.monotonic() - t0)
    log.info("backend: %d cameras", len(cameras))
    run_node(node, cfg.transport)
    return 0
