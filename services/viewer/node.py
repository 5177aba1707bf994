"""The viewer as a process node (``sigmaslam viewer``): every shown topic goes into the scene model (latest wins,
nothing queues up), and ``tick`` pushes the model's changes to the browser at ``viewer.draw_rate_hz``, so a slow
browser makes the drawing coarser, never the pipeline slower. The page's Pause / Resume buttons go out on
``control``. A message the model rejects is a drop of its subscription in ``stats/viewer``, logged at most once per
period. The draw timer and the subscription counters go out in ``stats/viewer``."""

from __future__ import annotations

import logging
import queue
import time

from shared import messages as m
from shared import topics
from shared.dataflow import Emit, Input, ProcessNode, RejectedMessage
from shared.process_description import ProcessDescription, ProcessStartError, Scheduling, Start
from shared.ratelimit import RateLimitedLog

log = logging.getLogger("sigmaslam.viewer")

SHOWN_TOPICS = (topics.STATE, topics.KEYFRAMES, topics.SUBMAP, topics.FRAME, topics.DEPTH_STEREO, topics.DEPTH_FUSED,
                topics.LANDMARKS, topics.STATS, topics.STREAM_END, topics.MAP_GRID)


class ViewerNode(ProcessNode):
    name = "viewer"
    inputs = tuple(Input(t, "on_message", note="shown") for t in SHOWN_TOPICS)
    outputs = (topics.CONTROL,)
    output_notes = {topics.CONTROL.key: "the page's pause and resume buttons"}

    def __init__(self, vcfg, model, server=None, clock=time.monotonic) -> None:
        """``server``: the viser server to draw into (None: keep the model only, e.g. in tests)."""
        self.vcfg, self.model, self.clock = vcfg, model, clock
        self.period_s = 1.0 / max(vcfg.draw_rate_hz, 1e-3)
        self.next_draw = clock()
        self._controls: queue.SimpleQueue[str] = queue.SimpleQueue()  # from the page's thread
        self._seq = 0
        self._draw_errors = RateLimitedLog(log)
        self.drawer, self.server = None, server
        if server is not None:
            from services.viewer.drawer import SceneDrawer

            self.drawer = SceneDrawer(server, model, publish_control=self.publish_control, export_dir=vcfg.export_dir,
                                      follow=vcfg.follow, frustum_scale_m=vcfg.frustum_scale_m)

    def publish_control(self, command: str) -> None:
        """Called by the page's buttons (another thread): sent on ``control`` at the next tick."""
        self._controls.put(command)

    def on_message(self, msg: m.Message) -> None:
        try:
            self.model.apply(msg)
        except ValueError as exc:
            raise RejectedMessage(f"a {type(msg).__name__} the scene model refuses: {exc}") from None

    def tick(self) -> list[Emit]:
        out = []
        while not self._controls.empty():
            command = self._controls.get()
            out.append(Emit(topics.CONTROL, m.Control(header=m.Header(stamp_ns=time.time_ns(), seq=self._seq, frame_id=""),
                                                      target=self.vcfg.player_target, command=command)))
            self._seq += 1
            log.info("sent %r to %r", command, self.vcfg.player_target)
        now = self.clock()
        if self.drawer is not None and now >= self.next_draw:
            self.next_draw = max(self.next_draw + self.period_s, now)
            with self.timer("draw", budget_ms=1e3 * self.period_s):
                try:
                    self.drawer.draw(self.model.take_update())
                except Exception as exc:  # a drawing error must not end the viewer: log (rate-limited), go on
                    self._draw_errors.warning("drawing failed: %s: %s", type(exc).__name__, exc)
        return out

    def close(self) -> list[Emit]:
        if self.server is not None:
            self.server.stop()
        return []


def build_model(cfg):
    """The scene model of the system config ``cfg``: the rig (viewer.rig, else the pipeline's rig section) and the
    ground truth. A bad viewer.rig or ground-truth file is an error naming the file; an unusable pipeline rig only a
    warning (frusta then come from the depth frames' K and T_SC)."""
    from services.viewer.scene_model import ViewerModel
    from shared.camera import CalibrationError, load_rig
    from shared.euroc import read_trajectory
    from shared.rig import load_rig_config

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


def _build(cfg, start: Start) -> ViewerNode:
    from shared.camera import CalibrationError
    from shared.euroc import TrajectoryFileError

    try:
        model = build_model(cfg)
    except (CalibrationError, TrajectoryFileError) as exc:
        raise ProcessStartError(str(exc)) from exc
    import viser  # imported here: reading the descriptions stays fast

    vcfg = cfg.viewer
    try:
        server = viser.ViserServer(host=vcfg.host, port=vcfg.port, label="sigmaslam", verbose=False)
    except OSError as exc:
        raise ProcessStartError(f"cannot serve on {vcfg.host}:{vcfg.port}: {exc}", code=1) from exc
    return ViewerNode(vcfg, model, server)


DESCRIPTION = ProcessDescription(
    name="viewer", node=ViewerNode, build=_build,
    scheduling=Scheduling(sched="idle"),  # CPU time nobody else wants
    ready=lambda node, cfg: f"viewer: http://{cfg.viewer.host}:{node.server.get_port()} (namespace "
                            f"{cfg.transport.namespace})",
    help="web viewer (viser): submap meshes, trajectories, live images, stats")
