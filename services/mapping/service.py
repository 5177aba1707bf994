"""``sigmaslam mapping [CONFIG] [--out DIR]``: the mapping node (services/mapping/node.py) as a process over Zenoh.

estimator/state, estimator/keyframes, depth/stereo or depth/fused (``mapping.depth_topic``),
estimator/trajectory_final -> map/submap, map/field, map/o2p_points; with an output folder, mesh.ply, submaps/,
map/dense.npz and mapping.json there.
"""

from __future__ import annotations

import argparse
import logging

from services.mapping.node import make_node
from services.system_config import load_system_config
from shared import topics
from transport.runner import run_node

log = logging.getLogger("sigmaslam.mapping")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", nargs="?", help="YAML system config (default: built-in defaults)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")
    p.add_argument("--out", metavar="DIR", help="write mesh.ply, submaps/, map/dense.npz here at exit (overrides mapping.output_dir)")


def main(args: argparse.Namespace) -> int:
    sys_cfg = load_system_config(args.config, args.set)
    cfg = sys_cfg.mapping  # depth_topic and pose_source were checked by the loader
    from shared.supervision import restart_count

    node = make_node(cfg, args.out or cfg.output_dir, restarts=restart_count())
    from services.mapping.integrate import warm_up

    warm_up(cfg.sensor)
    run_node(node, sys_cfg.transport,
             ready=lambda: print(f"mapping: {cfg.depth_topic} -> {topics.SUBMAP.key}", flush=True))
    return 0
