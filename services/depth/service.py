"""``sigmaslam depth [CONFIG]``: sensors/frame + estimator/state + estimator/keyframes + estimator/landmarks
(keep-latest; the MVS network's sparse prior) -> depth/stereo and
depth/fused (DepthFrame: depth, sigma, K and T_SC of the rectified left camera, T_WC when the estimator
knows the frame's pose, identity otherwise).

Thin shell around :class:`services.depth.pipeline.DepthPipeline`. Frames wait in a keep-latest queue of
one: a frame that a newer one replaces before the service gets to it is dropped and counted (the
``sensors/frame`` queue's drops in ``stats/depth``), so the service never blocks upstream and runs at
``depth.rate_hz`` at most. A frame waits up to ``depth.pose_wait_s`` for its estimator state. A frame
that cannot be processed (missing camera, wrong image size) is dropped, counted and logged.
"""
from __future__ import annotations

import argparse
import logging
import threading
import time
from collections import OrderedDict

import numpy as np

from services.depth.pipeline import DepthPipeline, DepthResult
from services.depth.weights import WeightsError
from services.system_config import load_system_config
from shared import topics
from shared.camera import CalibrationError
from shared.codec import Header
from shared.messages import DepthFrame, MultiCameraFrame
from shared.rig import load_rig_config
from transport.node import Node
from transport.queues import Empty

log = logging.getLogger("sigmaslam.depth")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", nargs="?", help="YAML system config (default: built-in defaults)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")


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
                      K=pipe.K, T_WC=np.eye(4) if res.T_WC is None else res.T_WC, T_SC=pipe.T_SC, source=source)


class PoseBook:
    """T_WS of recent estimator states by stamp (filled from the Zenoh thread)."""

    def __init__(self, size: int = 256) -> None:
        self._poses: OrderedDict[int, np.ndarray] = OrderedDict()
        self._lock = threading.Lock()
        self._size = size

    def add(self, msg) -> None:
        if msg.status in ("initialising", "lost", "reset"):
            return
        with self._lock:
            self._poses[int(msg.header.stamp_ns)] = np.asarray(msg.T_WS)
            while len(self._poses) > self._size:
                self._poses.popitem(last=False)

    def get(self, stamp_ns: int) -> np.ndarray | None:
        with self._lock:
            return self._poses.get(int(stamp_ns))


def main(args: argparse.Namespace) -> int:
    cfg = load_system_config(args.config, args.set)
    dc = cfg.depth
    try:
        cams = {c.name: c for c in load_rig_config(cfg.rig)}
        pipe = DepthPipeline(dc, cams[dc.left_camera], None if dc.mono else cams[dc.right_camera])
    except KeyError as exc:
        print(f"sigmaslam depth: camera {exc} not in the rig (depth.mono=true for a one-camera rig)", flush=True)
        return 2
    except (CalibrationError, FileNotFoundError, WeightsError) as exc:
        print(f"sigmaslam depth: {exc}", flush=True)
        return 2
    log.info("depth: method %s (stereo gain %.3f, MVS %s), %dx%d, f %.1f px, baseline %.3f m", pipe.method,
             pipe.stereo_gain, "on" if pipe.mvs_net is not None else "off", dc.width, dc.height, pipe.f_px, pipe.baseline_m)
    t_warm = time.monotonic()
    pipe.warm_up()  # before the node's first heartbeat: a player waiting for it starts once depth is ready
    log.info("depth: networks warmed up in %.1f s", time.monotonic() - t_warm)
    right_name = None if dc.mono else dc.right_camera
    no_mvs = [0]  # depth.mono: frames without MVS depth yet (no pose or no source views), nothing published
    poses = PoseBook()
    lock = threading.Lock()
    dropped_bad = 0

    def remember(frame: MultiCameraFrame) -> None:
        try:
            left, _ = frame_images(frame, dc.left_camera, right_name)
        except ValueError:
            return
        with lock:
            pipe.remember_frame(int(frame.header.stamp_ns), left)

    with Node("depth", cfg.transport) as node:
        frames = node.subscriber(topics.FRAME, depth=1)
        node.subscriber(topics.STATE, handler=poses.add)
        if pipe.mvs_net is not None:
            node.subscriber(topics.FRAME, handler=remember)
        keyframes = node.subscriber(topics.KEYFRAMES)
        landmarks = node.subscriber(topics.LANDMARKS, depth=1)
        # counters in stats/depth, reported as queues: frames with MVS depth; landmark pixels in their priors
        # (received: total, dropped: landmarks left out, depth: pixels in the last MVS frame's prior)
        prior = {"frames": 0, "points": 0, "last": 0}
        node.stats.add_queue("mvs_frames", lambda: (prior["frames"], 0, 0))
        node.stats.add_queue("mvs_prior_points", lambda: (prior["points"], pipe.prior_rejected, prior["last"]))
        if dc.mono:
            node.stats.add_queue("mono_without_mvs", lambda: (no_mvs[0], no_mvs[0], 0))
        pub_stereo = node.publisher(topics.DEPTH_STEREO)
        pub_fused = node.publisher(topics.DEPTH_FUSED)
        timer = node.timer("depth", budget_ms=dc.budget_ms)
        print(f"depth: running ({pipe.method}, {dc.rate_hz:g} Hz) on namespace {cfg.transport.namespace}", flush=True)
        period = 1.0 / dc.rate_hz
        next_t = time.monotonic()
        seq = 0
        while not node.stopped:
            if node.wait(max(0.0, next_t - time.monotonic())):
                break
            try:
                frame = frames.get(timeout=0.1)
            except Empty:
                continue
            next_t = time.monotonic() + period
            stamp = int(frame.header.stamp_ns)
            deadline = time.monotonic() + (dc.mono_pose_wait_s if dc.mono else dc.pose_wait_s)
            while poses.get(stamp) is None and time.monotonic() < deadline and not node.stopped:
                time.sleep(0.002)
            for kf in keyframes.drain():
                with lock:
                    pipe.update_keyframes(kf.stamps_ns, kf.T_WS)
            for lm in landmarks.drain()[-1:]:
                try:
                    pipe.update_landmarks(lm.p_W, lm.last_seen_ns, lm.num_observations)
                except ValueError as exc:
                    landmarks.queue.count_drop()
                    log.warning("depth: landmarks %d dropped: %s", lm.header.stamp_ns, exc)
            try:
                left, right = frame_images(frame, dc.left_camera, right_name)
                with timer:  # process() reads only the keyframe views, which this thread alone changes
                    res = pipe.process(stamp, left, right, poses.get(stamp))
                    if dc.inject_delay_ms > 0:  # test/bench overload knob (docs/reliability.md)
                        time.sleep(dc.inject_delay_ms / 1e3)
            except (ValueError, RuntimeError) as exc:  # e.g. a camera missing or images of the wrong size
                dropped_bad += 1
                log.warning("depth: frame %d dropped (%d so far): %s", stamp, dropped_bad, exc)
                continue
            if res.mvs is not None:
                prior["frames"] += 1
                prior["points"] += res.n_prior
                prior["last"] = res.n_prior
                if prior["frames"] % 50 == 1:
                    log.info("depth: MVS prior of %d landmark pixels (mean %.1f over %d MVS frames)", res.n_prior,
                             prior["points"] / prior["frames"], prior["frames"])
            if res.fused is None:  # depth.mono before MVS has a pose and source views
                no_mvs[0] += 1
                continue
            name = f"{dc.left_camera}_rect"
            pub_stereo.publish(depth_message(res, "stereo", pipe, stamp, seq, name))
            pub_fused.publish(depth_message(res, "fused", pipe, stamp, seq, name))
            seq += 1
    return 0
