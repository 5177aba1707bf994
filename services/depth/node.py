"""The depth process as a transport-free node: sensors/frame + estimator/state + estimator/keyframes +
estimator/landmarks (keep-latest; the MVS network's sparse prior) -> depth/stereo and depth/fused (DepthFrame:
depth, sigma, K and T_SC of the rectified left camera, T_WC when the estimator knows the frame's pose, identity
otherwise).

:class:`DepthNode` wraps :class:`services.depth.pipeline.DepthPipeline`. Frames wait in a keep-latest queue of one
and are taken on a schedule of 1 / ``depth.rate_hz`` (a frame that took longer than that is made up by taking the
next one sooner: transport.runner.next_trigger_time): a frame that a newer one replaces first is dropped and counted
(the ``sensors/frame`` queue's drops in ``stats/depth``), so the service never blocks upstream. A frame waits up to
``depth.pose_wait_s`` for its estimator state. A frame that cannot be processed (missing camera, wrong image
size) is dropped, counted and logged. With MVS on, every frame's left image is remembered (a second, keep-all
subscription) for the keyframe views.
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict
from typing import TYPE_CHECKING

import numpy as np

from shared import topics
from shared.codec import Header
from shared.dataflow import Emit, Input, ProcessNode
from shared.messages import DepthFrame, EstimatorState, Keyframes, Landmarks, MultiCameraFrame
from shared.process_description import ProcessDescription, ProcessStartError, Scheduling, Start

if TYPE_CHECKING:
    from services.depth.pipeline import DepthPipeline, DepthResult

log = logging.getLogger("sigmaslam.depth")


def frame_images(frame: MultiCameraFrame, left: str, right: str | None) -> tuple[np.ndarray, np.ndarray | None]:
    """The left and right images of a frame (right None when ``right`` is None: depth.mono)."""
    names = list(frame.camera_names)
    if left not in names or (right is not None and right not in names):
        raise ValueError(f"frame has cameras {names}, needs {left!r}" + ("" if right is None else f" and {right!r}"))
    return frame.images[names.index(left)], None if right is None else frame.images[names.index(right)]


def depth_message(res: DepthResult, which: str, pipe: DepthPipeline, stamp_ns: int, seq: int, frame_id: str) -> DepthFrame:
    if res.stereo is None:  # depth.mono: the MVS depth on both topics
        (depth, sigma), source = res.fused, "mvs"
    else:
        depth, sigma = res.stereo if which == "stereo" else res.fused
        source = "stereo" if which == "stereo" or res.mvs is None else "fused"
    return DepthFrame(header=Header(stamp_ns=stamp_ns, seq=seq, frame_id=frame_id),
                      depth=np.ascontiguousarray(depth, np.float32), sigma=np.ascontiguousarray(sigma, np.float32),
                      K=pipe.K, T_WC=np.eye(4) if res.T_WC is None else res.T_WC, T_SC=pipe.T_SC, source=source,
                      surface_max_relative_sigma=res.surface_max_relative_sigma)


class PoseBook:
    """T_WS of recent estimator states by stamp (the node's handlers all run in one thread: no lock)."""

    def __init__(self, size: int = 256) -> None:
        self._poses: OrderedDict[int, np.ndarray] = OrderedDict()
        self._size = size

    def add(self, msg) -> None:
        if msg.status in ("initialising", "lost", "reset"):
            return
        self._poses[int(msg.header.stamp_ns)] = np.asarray(msg.T_WS)
        while len(self._poses) > self._size:
            self._poses.popitem(last=False)

    def get(self, stamp_ns: int) -> np.ndarray | None:
        return self._poses.get(int(stamp_ns))



class DepthNode(ProcessNode):
    name = "depth"
    stage = "depth"
    inputs = (
        Input(topics.FRAME, "on_frame", role="trigger", depth=1, note="the frame to work on, at depth.rate_hz"),
        Input(topics.STATE, "on_state", wait_until_trigger_stamp=True, note="the frame's pose"),
        Input(topics.FRAME, "remember", policy="all", when="MVS on", note="left images for the keyframe views"),
        Input(topics.KEYFRAMES, "on_keyframes", note="MVS source views"),
        Input(topics.LANDMARKS, "on_landmarks", depth=1, note="the MVS prior"),
    )
    output_notes = {topics.DEPTH_STEREO.key: "each processed frame", topics.DEPTH_FUSED.key: "each processed frame"}
    outputs = (topics.DEPTH_STEREO, topics.DEPTH_FUSED)

    def __init__(self, dc, pipe: DepthPipeline) -> None:
        self.dc, self.pipe = dc, pipe
        self.budget_ms = dc.budget_ms
        self.wait_s = dc.mono_pose_wait_s if dc.mono else dc.pose_wait_s
        self.trigger_period_s = 1.0 / dc.rate_hz
        self.right_name = None if dc.mono else dc.right_camera
        self.poses = PoseBook()
        self.dropped_bad = 0
        self.dropped_landmarks = 0
        self.no_mvs = 0  # depth.mono: frames without MVS depth yet (no pose or no source views), nothing published
        # frames with MVS depth; landmark pixels in their priors (total; in the last MVS frame)
        self.prior = {"frames": 0, "points": 0, "last": 0}
        self.seq = 0
        used = ["on_frame", "on_state", "on_keyframes", "on_landmarks"]
        if pipe.mvs_net is not None:
            used.append("remember")
        self.use_inputs(used)

    def counters(self) -> dict:
        out = {"mvs_frames": lambda: self.prior["frames"],  # MVS frames with a landmark prior
               "mvs_prior_points": lambda: self.prior["points"],  # landmark points given to it, and refused
               "mvs_prior_points_rejected": lambda: self.pipe.prior_rejected,
               "landmarks_refused": lambda: self.dropped_landmarks,
               # pixels of the published maps: placing a surface, and too uncertain to (depth.max_relative_sigma: free space only)
               "confident_pixels": lambda: self.pipe.confident_px,
               "uncertain_pixels": lambda: self.pipe.uncertain_px, "flying_pixels": lambda: self.pipe.flying_px}
        if self.dc.mono:
            out["mono_without_mvs"] = lambda: self.no_mvs
        return out

    def on_state(self, msg: EstimatorState) -> None:
        self.poses.add(msg)

    def remember(self, frame: MultiCameraFrame) -> None:
        try:
            left, _ = frame_images(frame, self.dc.left_camera, self.right_name)
        except ValueError:
            return
        self.pipe.remember_frame(int(frame.header.stamp_ns), left)

    def on_keyframes(self, kf: Keyframes) -> None:
        self.pipe.update_keyframes(kf.stamps_ns, kf.T_WS)

    def on_landmarks(self, lm: Landmarks) -> None:
        try:
            self.pipe.update_landmarks(lm.p_W, lm.last_seen_ns, lm.num_observations)
        except ValueError as exc:
            self.dropped_landmarks += 1
            log.warning("depth: landmarks %d dropped: %s", lm.header.stamp_ns, exc)

    def on_frame(self, frame: MultiCameraFrame) -> list[Emit]:
        dc, stamp = self.dc, int(frame.header.stamp_ns)
        try:
            left, right = frame_images(frame, dc.left_camera, self.right_name)
            res = self.pipe.process(stamp, left, right, self.poses.get(stamp))
            if dc.inject_delay_ms > 0:  # test/bench overload knob (docs/reliability.md)
                time.sleep(dc.inject_delay_ms / 1e3)
        except (ValueError, RuntimeError) as exc:  # e.g. a camera missing or images of the wrong size
            self.dropped_bad += 1
            log.warning("depth: frame %d dropped (%d so far): %s", stamp, self.dropped_bad, exc)
            return []
        if res.mvs is not None:
            p = self.prior
            p["frames"] += 1
            p["points"] += res.n_prior
            p["last"] = res.n_prior
            if p["frames"] % 50 == 1:
                log.info("depth: MVS prior of %d landmark pixels (mean %.1f over %d MVS frames)", res.n_prior,
                         p["points"] / p["frames"], p["frames"])
        if res.fused is None:  # depth.mono before MVS has a pose and source views
            self.no_mvs += 1
            return []
        name = f"{dc.left_camera}_rect"
        out = [Emit(topics.DEPTH_STEREO, depth_message(res, "stereo", self.pipe, stamp, self.seq, name)),
               Emit(topics.DEPTH_FUSED, depth_message(res, "fused", self.pipe, stamp, self.seq, name))]
        self.seq += 1
        return out


def _build(cfg, start: Start) -> DepthNode:
    from services.depth.pipeline import pipeline_for_rig
    from services.depth.weights import WeightsError
    from shared.camera import CalibrationError

    dc = cfg.depth
    try:
        pipe = pipeline_for_rig(dc, start.rig(cfg))
    except (CalibrationError, FileNotFoundError, WeightsError, ValueError) as exc:
        raise ProcessStartError(str(exc)) from exc
    log.info("depth: method %s (stereo gain %.3f, MVS %s), %dx%d, f %.1f px, baseline %.3f m", pipe.method,
             pipe.stereo_gain, "on" if pipe.mvs_net is not None else "off", dc.width, dc.height, pipe.f_px,
             pipe.baseline_m)
    return DepthNode(dc, pipe)


def _warm_up(node: DepthNode) -> None:
    t0 = time.monotonic()
    node.pipe.warm_up()  # before the node's first heartbeat: a player waiting for it starts once depth is ready
    log.info("depth: networks warmed up in %.1f s", time.monotonic() - t0)


DESCRIPTION = ProcessDescription(
    name="depth", node=DepthNode, build=_build, warm_up=_warm_up, in_process=True,
    scheduling=Scheduling(nice=19),  # what the path to a pose and other work leave; runs at depth.rate_hz at most
    ready=lambda node, cfg: f"depth: running ({node.pipe.method}, {node.dc.rate_hz:g} Hz) on namespace "
                            f"{cfg.transport.namespace}",
    help="stereo + MVS depth with learned sigma, fused: sensors/frame -> depth/stereo, depth/fused")
