"""``sigmaslam depth [CONFIG]``: the depth node (services/depth/node.py) as a process over Zenoh.

sensors/frame + estimator/state + estimator/keyframes + estimator/landmarks -> depth/stereo, depth/fused.
"""

from __future__ import annotations

import argparse
import logging
import time

from services.depth.node import DepthNode
from services.depth.pipeline import pipeline_for_rig
from services.depth.weights import WeightsError
from services.system_config import load_system_config
from shared.camera import CalibrationError
from shared.rig import load_rig_config
from transport.runner import run_node

log = logging.getLogger("sigmaslam.depth")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", nargs="?", help="YAML system config (default: built-in defaults)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")


def main(args: argparse.Namespace) -> int:
    cfg = load_system_config(args.config, args.set)
    dc = cfg.depth
    try:
        pipe = pipeline_for_rig(dc, load_rig_config(cfg.rig))
    except (CalibrationError, FileNotFoundError, WeightsError, ValueError) as exc:
        print(f"sigmaslam depth: {exc}", flush=True)
        return 2
    log.info("depth: method %s (stereo gain %.3f, MVS %s), %dx%d, f %.1f px, baseline %.3f m", pipe.method,
             pipe.stereo_gain, "on" if pipe.mvs_net is not None else "off", dc.width, dc.height, pipe.f_px, pipe.baseline_m)
    t_warm = time.monotonic()
    pipe.warm_up()  # before the node's first heartbeat: a player waiting for it starts once depth is ready
    log.info("depth: networks warmed up in %.1f s", time.monotonic() - t_warm)
    run_node(DepthNode(dc, pipe), cfg.transport, ready=lambda: print(
        f"depth: running ({pipe.method}, {dc.rate_hz:g} Hz) on namespace {cfg.transport.namespace}", flush=True))
    return 0
