"""``sigmaslam viewer [CONFIG]``: the viser web page of submap meshes, trajectories and live sensors.

Receiving and drawing are decoupled: Zenoh callbacks only store the latest data in a
:class:`~services.viewer.scene_model.ViewerModel` (per-submap latest wins, images latest wins, nothing
queues up), and a drawing loop takes the changes at ``viewer.draw_rate_hz`` and pushes them to the
browser. A slow browser therefore makes the drawing coarser, never the pipeline slower. The draw
timer and the subscription counters go out in ``stats/viewer``.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time

from services.system_config import SystemConfig, load_system_config
from services.viewer.config import ViewerConfig
from services.viewer.node import SHOWN_TOPICS, ViewerNode
from services.viewer.scene_model import ViewerModel
from shared import messages as m
from shared import topics
from shared.camera import CalibrationError, load_rig
from shared.euroc import TrajectoryFileError, read_trajectory
from shared.rig import load_rig_config
from transport.config import TransportConfig
from transport.node import Node
from transport.pubsub import RateLimitedLog, Subscriber

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


def _counting_handler(model: ViewerModel, bad_log: RateLimitedLog):
    """model.apply for one subscription; a message the model rejects is counted as a drop of that
    subscription (stats/viewer queue_dropped) and logged, never raised into Zenoh."""
    holder: dict[str, Subscriber] = {}

    def handle(msg: m.Message) -> None:
        try:
            model.apply(msg)
        except ValueError as exc:
            sub = holder.get("sub")
            if sub is not None:
                sub.queue.count_drop()
            bad_log.warning("dropped a %s: %s", type(msg).__name__, exc)

    handle.holder = holder  # type: ignore[attr-defined]
    return handle


def run(vcfg: ViewerConfig, tcfg: TransportConfig, model: ViewerModel) -> int:
    import viser  # imported here: `sigmaslam --help` stays fast

    from services.viewer.drawer import SceneDrawer

    try:
        server = viser.ViserServer(host=vcfg.host, port=vcfg.port, label="sigmaslam", verbose=False)
    except OSError as exc:
        print(f"sigmaslam viewer: cannot serve on {vcfg.host}:{vcfg.port}: {exc}", file=sys.stderr)
        return 1
    try:
        with Node("viewer", tcfg, declared=ViewerNode) as node:
            control = node.publisher(topics.CONTROL)

            def publish_control(command: str) -> None:
                control.publish(m.Control(header=m.Header(stamp_ns=time.time_ns(), seq=control.next_seq, frame_id=""),
                                          target=vcfg.player_target, command=command))
                log.info("sent %r to %r", command, vcfg.player_target)

            bad_input = RateLimitedLog(log)
            for topic in SHOWN_TOPICS:
                handler = _counting_handler(model, bad_input)
                handler.holder["sub"] = node.subscriber(topic, handler=handler)
            drawer = SceneDrawer(server, model, publish_control=publish_control, export_dir=vcfg.export_dir,
                                 follow=vcfg.follow, frustum_scale_m=vcfg.frustum_scale_m)
            draw_timer = node.timer("draw", budget_ms=1000.0 / max(vcfg.draw_rate_hz, 1e-3))
            print(f"viewer: http://{vcfg.host}:{server.get_port()} (namespace {tcfg.namespace})", flush=True)
            period = 1.0 / max(vcfg.draw_rate_hz, 1e-3)
            draw_errors = RateLimitedLog(log)
            while not node.wait(period):
                with draw_timer:
                    try:
                        drawer.draw(model.take_update())
                    except Exception as exc:  # a drawing error must not end the viewer: log (rate-limited), go on
                        draw_errors.warning("drawing failed: %s: %s", type(exc).__name__, exc)
    finally:
        server.stop()
    return 0
