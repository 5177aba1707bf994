"""``sigmaslam viewer [CONFIG]``: the viser web page of submap meshes, trajectories and live sensors.

The viewer node (services/viewer/node.py) run over Zenoh: messages only update a
:class:`~services.viewer.scene_model.ViewerModel` (per-submap latest wins, images latest wins, nothing
queues up), and the node's tick pushes the changes to the browser at ``viewer.draw_rate_hz``. A slow browser
therefore makes the drawing coarser, never the pipeline slower. The draw timer, the subscription counters and
the rejected messages go out in ``stats/viewer``.
"""

from __future__ import annotations

import argparse
import logging
import sys

from services.system_config import SystemConfig, load_system_config
from services.viewer.config import ViewerConfig
from services.viewer.node import ViewerNode
from services.viewer.scene_model import ViewerModel
from shared.camera import CalibrationError, load_rig
from shared.euroc import TrajectoryFileError, read_trajectory
from shared.rig import load_rig_config
from transport.config import TransportConfig
from transport.runner import run_node

log = logging.getLogger("sigmaslam.viewer")



def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", nargs="?", help="YAML system config (default: built-in defaults)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field, e.g. viewer.port=8081")


def build_model(cfg: SystemConfig) -> ViewerModel:
    """The scene model with the rig (viewer.rig, else the pipeline's rig section) and ground truth.

    A bad viewer.rig or ground-truth file is an error naming the file; an unusable pipeline rig only a
    warning (frusta then come from the depth frames' K and T_SC)."""
    vcfg = cfg.viewer
    if vcfg.rig:
        cameras = load_rig(vcfg.rig)
    else:
        try:
            cameras = load_rig_config(cfg.rig)
        except CalibrationError as exc:
            log.warning("no rig for the camera frusta (%s): using the depth frames' K and T_SC", exc)
            cameras = None
    gt = read_trajectory(vcfg.ground_truth) if vcfg.ground_truth else None
    return ViewerModel(vcfg, cameras, gt)


def main(args: argparse.Namespace) -> int:
    cfg = load_system_config(args.config, args.set)
    try:
        model = build_model(cfg)
    except (CalibrationError, TrajectoryFileError) as exc:
        print(f"sigmaslam viewer: {exc}", file=sys.stderr)
        return 2
    return run(cfg.viewer, cfg.transport, model)


def run(vcfg: ViewerConfig, tcfg: TransportConfig, model: ViewerModel) -> int:
    import viser  # imported here: `sigmaslam --help` stays fast

    try:
        server = viser.ViserServer(host=vcfg.host, port=vcfg.port, label="sigmaslam", verbose=False)
    except OSError as exc:
        print(f"sigmaslam viewer: cannot serve on {vcfg.host}:{vcfg.port}: {exc}", file=sys.stderr)
        return 1
    try:
        run_node(ViewerNode(vcfg, model, server), tcfg, ready=lambda: print(
            f"viewer: http://{vcfg.host}:{server.get_port()} (namespace {tcfg.namespace})", flush=True))
    finally:
        server.stop()
    return 0
