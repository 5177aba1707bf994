"""The back end as a transport-free process node, and its composition root.

sensors/imu (keep-all) + frontend/frame -> estimator/window, estimator/keyframes and estimator/landmarks after each
keyframe's window optimisation; with loop closure, frontend/keyframe_features and estimator/state (the published
poses) in and, at the end of the stream, estimator/trajectory_final out; with occupancy-to-point factors, map/field,
map/o2p_points and depth/stereo in.

The back end handles only the frames its estimator makes keyframes of (``WindowedVioEstimator.wants_frame``): the
state of every frame is published by the per-frame fast path in the frontend's process
(services/backend/odometry_node.py, run by services/frontend/process_node.py) from the window this node publishes, so no frame waits for a window optimisation.

:class:`BackendNode` is the back end's composition root: the one place that builds what the back end is made of
from the system config and hands each part its collaborators in its constructor (the seams are the protocols of
services/backend/protocols.py): the windowed VIO estimator, the occupancy-to-point terms (``cfg.o2p.enabled``) and
the loop closer (``cfg.loop.enabled``); :class:`BackendShell` runs the estimator and the terms per frame. Run over
Zenoh by ``sigmaslam backend`` (services/backend/service.py) or in one process by
:class:`shared.dataflow.InProcessRunner`.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path

import numpy as np

from shared.backlog import shed_backlog
from services.backend.cameras import BackendCamera
from services.backend.estimator import BackendInputError, WindowedVioEstimator, camera_from_calib
from services.backend.frame_result import FrameResult
from services.backend.imu_factors import ImuDataError
from services.backend.loop.backend_loop import LoopClosingBackend, PublishedFrame
from services.backend.loop.history import KeyframeHistory
from services.backend.loop.loop_closer import LoopCloser
from services.backend.loop.loop_thread import ThreadedLoopCloser
from services.backend.loop.saved_map import SparseMapError, load_sparse
from shared.config import ConfigError
from shared.map_folder import SPARSE_FILE, run_map_dir, sparse_path
from services.backend.o2p_terms import OccupancyTerms
from services.backend.outputs import keyframes_message, landmarks_message, state_message
from shared.lookup_camera import LookupCamera
from shared import topics
from shared.dataflow import Emit, Input, ProcessNode
from shared.messages import (DepthFrame, EstimatorState, EstimatorWindow, FeatureFrame, Header, ImuSample,
                             KeyframeFeatures, Keyframes, Landmarks, OccupancyField, StreamEnd)

log = logging.getLogger("sigmaslam.backend")


def backend_cameras(cameras) -> list[BackendCamera]:
    """The rig's cameras (shared.rig calibrations) as the estimator and the loop closer use them: undistortion by
    table lookup (the exact Newton inverse costs ~10 ms per frame at 300 observations)."""
    return [camera_from_calib(dataclasses.replace(c, camera=LookupCamera(c.camera))) for c in cameras]


class BackendShell:
    """Per-frame logic of the service without the transport: ``estimator`` and, when occupancy-to-point factors are
    on, ``o2p`` (the estimator's extra-factor source, fed here with map and depth inputs). ``restarted``: after a
    supervisor restart, the first state says 'reset'."""

    def __init__(self, estimator: WindowedVioEstimator, o2p: OccupancyTerms | None = None,
                 restarted: bool = False) -> None:
        self.estimator = estimator
        self.o2p = o2p
        self.restarted = restarted
        self.dropped = 0
        self.seq = 0
        self.newest_imu_ns = -1
        self.landmarks: Landmarks | None = None  # of the last keyframe processed, until take_landmarks()
        self.last_result: FrameResult | None = None  # the estimator's raw result of the last frame processed

    def add_map_input(self, msg) -> None:
        """map/field (OccupancyField), depth/stereo (DepthFrame) or map/o2p_points (SubmapPoints) for o2p."""
        if self.o2p is None:
            return
        try:
            if isinstance(msg, DepthFrame):
                T_WS = None if np.allclose(msg.T_WC, np.eye(4)) else msg.T_WC @ np.linalg.inv(msg.T_SC)
                est = self.estimator
                self.o2p.add_depth(msg.header.stamp_ns, msg.depth, msg.sigma, msg.K, msg.T_SC, T_WS, est.stamps, est.values)
            elif isinstance(msg, OccupancyField):
                self.o2p.add_field(msg)
            else:
                self.o2p.add_submap_points(msg.submap_id, msg.points_M, msg.sigma)
        except ValueError as exc:
            self.o2p.counts["dropped_bad_input"] += 1
            log.warning("o2p input %s dropped: %s", type(msg).__name__, exc)

    def add_imu(self, sample) -> None:
        self.estimator.add_imu(int(sample.header.stamp_ns), sample.omega_S, sample.acc_S)
        self.newest_imu_ns = max(self.newest_imu_ns, int(sample.header.stamp_ns))

    def process(self, frame: FeatureFrame) -> tuple[EstimatorState, Keyframes | None] | None:
        msgs = self._process(frame)
        if msgs is not None and self.restarted:
            # a restarted back end lost its window: its first state says so (consumers treat 'reset' like
            # 'initialising': no pose to use), then it re-initialises from scratch
            self.restarted = False
            log.warning("back end restarted: state history lost, re-initialising (status 'reset' at %d)",
                        msgs[0].header.stamp_ns)
            msgs = (dataclasses.replace(msgs[0], status="reset"), msgs[1])
        return msgs

    def _process(self, frame: FeatureFrame) -> tuple[EstimatorState, Keyframes | None] | None:
        stamp = int(frame.header.stamp_ns)
        if self.o2p is not None:
            self.o2p.note_frame(stamp, frame.landmark_ids)
        try:
            res = self.estimator.process_frame(stamp, frame.landmark_ids, frame.camera_index, frame.uv,
                                               bool(frame.is_keyframe))
        except (BackendInputError, ImuDataError) as exc:
            self.dropped += 1
            log.warning("feature frame %d dropped (%d so far): %s", stamp, self.dropped, exc)
            return None
        if res is None:  # not initialised yet (needs IMU before the first frame): say so, for lockstep players
            msg = EstimatorState(header=Header(stamp_ns=stamp, seq=self.seq, frame_id="W"), T_WS=np.eye(4),
                                 v_W=np.zeros(3), gyro_bias=np.zeros(3), acc_bias=np.zeros(3),
                                 covariance=np.full((15, 15), np.nan), status="initialising")
            self.seq += 1
            return msg, None
        self.last_result = res
        msgs = state_message(res, self.seq), keyframes_message(res, self.seq)
        self.landmarks = landmarks_message(res, self.seq)
        self.seq += 1
        return msgs

    def take_landmarks(self) -> Landmarks | None:
        """estimator/landmarks of the last frame processed if it was a keyframe (once)."""
        msg, self.landmarks = self.landmarks, None
        return msg

    def window_message(self, state: EstimatorState, T_corr: np.ndarray | None) -> EstimatorWindow:
        """estimator/window after the frame that gave ``state`` (its status; the pose from the estimator's own
        result, in W): the newest keyframe and the window's landmarks for the fast path."""
        res = self.last_result
        if state.status in ("initialising", "reset") or res is None:  # no state to anchor to: status alone
            return EstimatorWindow(header=state.header, T_WS=np.eye(4), v_W=np.zeros(3), gyro_bias=np.zeros(3),
                                   acc_bias=np.zeros(3), T_corr=np.eye(4), landmark_ids=np.zeros(0, np.int64),
                                   p_W=np.zeros((0, 3)),
                                   status="reset" if state.status == "reset" else "initialising")
        ids, p_W = self.estimator.window_points()
        return EstimatorWindow(header=state.header, T_WS=np.ascontiguousarray(res.T_WS, np.float64),
                               v_W=np.asarray(res.v_W, np.float64), gyro_bias=np.asarray(res.gyro_bias, np.float64),
                               acc_bias=np.asarray(res.acc_bias, np.float64),
                               T_corr=np.eye(4) if T_corr is None else np.ascontiguousarray(T_corr, np.float64),
                               landmark_ids=ids, p_W=np.ascontiguousarray(p_W, np.float64),
                               T_SC=np.zeros((0, 4, 4)) if res.T_SC is None else np.ascontiguousarray(res.T_SC),
                               time_offset_s=float(res.time_offset_s), status=state.status)



def saved_map_to_load(lc, restarted: bool) -> Path | None:
    """The sparse map a back end starts from: after a restart, its run's own last checkpoint
    (``loop.map_output``/map/sparse.npz, which holds the saved map it localised in, if any); else
    ``loop.prior_map``; None for neither. A configured ``prior_map`` that is not there is an error (ConfigError:
    the service stops with the message); a missing checkpoint only means starting afresh (logged)."""
    if restarted and lc.map_output:
        ckpt = run_map_dir(lc.map_output) / SPARSE_FILE
        if ckpt.is_file():
            log.warning("back end restarted: relocalising in this run's last saved map %s", ckpt)
            return ckpt
        log.warning("back end restarted without a saved map (%s): starting a new world frame", ckpt)
    if not lc.prior_map:
        return None
    path = sparse_path(lc.prior_map)
    if not path.is_file():
        raise ConfigError(f"loop.prior_map: {path} not found (a run's folder with map/sparse.npz, or the map/ "
                          "folder itself)")
    return path


class _LateBound:
    """A value handed to constructors before it exists, bound once right after (the root's one cycle)."""

    def __init__(self, what: str) -> None:
        self.what, self.value = what, None

    def bind(self, value):
        self.value = value
        return value

    def __call__(self):
        if self.value is None:
            raise RuntimeError(f"{self.what} read before it was built")
        return self.value


class BackendNode(ProcessNode):
    """The back end's process node and composition root: builds estimator, occupancy terms and loop closer from
    ``cfg`` (the system config), each with its collaborators in its constructor, and routes each input to them.

    Who needs whom: the estimator takes the occupancy terms (extra factors) and the loop closer's keyframe history
    (marginalisation listener); the history feeds the loop closer, which needs only the cameras; the occupancy terms
    take the loop closer's :class:`PublishedFrame` as their submap anchoring, and that reads the estimator's window
    when a submap is anchored. The one cycle (estimator -> terms -> anchoring -> estimator) is cut at its last link,
    which is only used while frames and map inputs flow, never during construction: the anchoring gets a late-bound
    provider of the estimator, bound as soon as the estimator is built. So the order is: cameras; loop closer,
    history and published frame; occupancy terms; estimator (provider bound); shell; loop-closing back end."""

    name = "backend"
    stage = "optimise"
    inputs = (
        Input(topics.FEATURES, "on_features", role="trigger", shed="shed", note="tracks of each frame"),
        Input(topics.IMU, "on_imu", wait_until_trigger_stamp=True, note="pre-integration, up to the frame's time"),
        Input(topics.MAP_FIELD, "on_map_input", policy="all", depth=64, when="o2p.enabled",
              note="submap fields for the occupancy-to-point factors"),
        Input(topics.MAP_O2P_POINTS, "on_map_input", when="o2p.enabled", note="map-to-map points"),
        Input(topics.DEPTH_STEREO, "on_map_input", depth=8, when="o2p.enabled", note="frame-to-map points"),
        Input(topics.KEYFRAME_FEATURES, "on_keyframe_features", when="loop.enabled", note="loop detection"),
        Input(topics.STATE, "on_state", policy="all", depth=256, when="loop.enabled",
              note="the fast path's published poses: the frames of the final trajectory"),
        Input(topics.STREAM_END, "on_stream_end", role="idle", when="loop.enabled",
              note="the final bundle adjustment after the last frame"),
    )
    outputs = (topics.WINDOW, topics.KEYFRAMES, topics.LANDMARKS, topics.TRAJECTORY_FINAL)
    output_notes = {topics.WINDOW.key: "after each keyframe's optimisation",
                    topics.KEYFRAMES.key: "after each keyframe's optimisation",
                    topics.LANDMARKS.key: "after each keyframe's optimisation",
                    topics.TRAJECTORY_FINAL.key: "once, after sensors/end (loop.enabled)"}

    def __init__(self, cfg, cameras, restarted: bool = False) -> None:
        bc, lc = cfg.backend, cfg.loop
        self.bc, self.budget_ms, self.wait_s = bc, bc.budget_ms, bc.imu_wait_s
        cams = backend_cameras(cameras)
        window = _LateBound("the back end's estimator")
        history = runner = published = None
        if lc.enabled:
            closer = LoopCloser(lc, cams)
            prior = saved_map_to_load(lc, restarted)
            if prior is not None:
                try:
                    closer.load_prior(load_sparse(prior))
                except SparseMapError as exc:
                    if not restarted:
                        raise ConfigError(f"loop.prior_map: {exc}") from exc
                    log.warning("saved map not usable (%s): starting a new world frame", exc)
                else:
                    log.info("localising in the saved map %s (%d keyframes)", prior, len(closer.prior))
            runner = ThreadedLoopCloser(closer, lc.synchronous)
            history = KeyframeHistory(listeners=[runner.submit_record])
            published = PublishedFrame(history, window, lc.correct_state, cfg.o2p.anchor_tolerance_ms)
        # no dense factors until the window has a metric scale (one camera: OccupancyTerms.window_factors)
        o2p = OccupancyTerms(cfg.o2p, anchoring=published) if cfg.o2p.enabled else None
        est = window.bind(WindowedVioEstimator(bc, cams, extra_factors=[o2p] if o2p is not None else [],
                                               on_marginalise=[history] if history is not None else []))
        self.shell = BackendShell(est, o2p, restarted)
        self.loop = LoopClosingBackend(self.shell, lc, history, runner, published) if lc.enabled else None
        if self.loop is not None:
            self.loop.session = {"source": str(cfg.rig.calibration), "restarted": bool(restarted),
                                 "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
        used = ["on_features", "on_imu"]
        if self.shell.o2p is not None:
            used.append("on_map_input")
        if self.loop is not None:
            used += ["on_keyframe_features", "on_state", "on_stream_end"]
        self.use_inputs(used)
        self.final_seq = 0
        self.skipped_frames = 0  # frames the estimator did not want (no keyframe): the fast path's alone
        self.skipped_keyframes = 0  # keyframes skipped to catch up (shed)

    @property
    def estimator(self) -> WindowedVioEstimator:
        return self.shell.estimator

    def shed(self, pending) -> tuple[list, int]:
        """Live only (the transport runner calls it before each feature frame with what waits): skip what
        :func:`shed_backlog` says, counting the keyframes among them."""
        kept, skipped = shed_backlog(pending, self.bc.max_backlog_frames, max_keyframes=self.bc.max_backlog_keyframes)
        self.skipped_keyframes += sum(bool(f.is_keyframe) for f in pending) - sum(bool(f.is_keyframe) for f in kept)
        return kept, skipped

    def counters(self) -> dict:
        return {"keyframes_skipped": lambda: self.skipped_keyframes}  # shed as backlog: never in the window

    def on_imu(self, sample: ImuSample) -> None:
        self.shell.add_imu(sample)

    def on_map_input(self, msg) -> None:
        self.shell.add_map_input(msg)

    def on_keyframe_features(self, msg: KeyframeFeatures) -> None:
        self.loop.add_keyframe_features(msg)

    def on_state(self, msg: EstimatorState) -> None:
        self.loop.record_state(msg)

    def on_features(self, frame: FeatureFrame) -> list[Emit]:
        stamp = int(frame.header.stamp_ns)
        if not self.estimator.wants_frame(stamp, bool(frame.is_keyframe)):
            if self.shell.o2p is not None:
                self.shell.o2p.note_frame(stamp, frame.landmark_ids)
            self.skipped_frames += 1
            return []
        msgs = self.shell.process(frame) if self.loop is None else self.loop.process(frame)
        out = []
        if msgs is not None:
            T_corr = self.loop.published.correction() if self.loop is not None else None
            out.append(Emit(topics.WINDOW, self.shell.window_message(msgs[0], T_corr)))
            if msgs[1] is not None:
                out.append(Emit(topics.KEYFRAMES, msgs[1]))
        if (lms := (self.shell if self.loop is None else self.loop).take_landmarks()) is not None:
            out.append(Emit(topics.LANDMARKS, lms))
        return out

    def _final(self, ends: list[StreamEnd]) -> list[Emit]:
        final = self.loop.poll_end(ends) if self.loop is not None else None
        return [] if final is None else [Emit(topics.TRAJECTORY_FINAL, final)]

    def on_stream_end(self, msg: StreamEnd) -> list[Emit]:
        return self._final([msg])

    def tick(self) -> list[Emit]:
        """While idle: the final trajectory once the stream has ended and no frame came for a while."""
        return self._final([])

    def close(self) -> list[Emit]:
        if self.shell.o2p is not None:  # how many dense factors the run used, and why others were not built
            log.info("o2p counts: %s", dict(sorted(self.shell.o2p.counts.items())))
        if self.loop is not None:
            self.loop.close()
        return []
