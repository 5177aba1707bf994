"""Loop closure inside the back end process: wraps a ``BackendShell`` (no transport in here).

Built by the back end's composition root (services/backend/node.py) from parts made before the estimator: the
keyframe history (the estimator's marginalisation listener), the :class:`ThreadedLoopCloser` it feeds and the
:class:`PublishedFrame`.

* the estimator's per-frame path only enqueues, so ``estimator/state`` is never delayed by verification or
  pose-graph solves;
* corrects the keyframe poses by the pose graph's latest correction ``T_W'W`` (when ``loop.correct_state``; the
  fast path applies the same correction to the published states); after a solve the keyframes message also
  carries every corrected pose-graph node;
* with occupancy-to-point factors on (the shell's ``o2p``), the :class:`PublishedFrame` is their submap anchoring:
  it binds each closed submap to the keyframe anchoring it (:meth:`PublishedFrame.anchor_of`); the map-to-map
  terms go to the pose graph;
* keeps the published causal poses (:meth:`LoopClosingBackend.record_state`), and at the end of the stream (:meth:`LoopClosingBackend.finish`) runs
  the final bundle adjustment over all keyframes with IMU, loop and map-to-map factors, giving the non-causal
  trajectory.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from typing import TYPE_CHECKING, Callable

import numpy as np
from gtsam.symbol_shorthand import X

from services.backend.loop.config import LoopConfig
from services.backend.loop.final_ba import bundle_adjust, follow_keyframes
from services.backend.loop.history import KeyframeHistory
from services.backend.loop.loop_thread import ThreadedLoopCloser
from services.backend.loop.verification import FeatureSet
from shared.geometry import inv_T
from shared.map_folder import SPARSE_FILE, UNALIGNED_FRAME, run_map_dir
from shared.messages import EstimatorState, FinalTrajectory, Header, KeyframeFeatures, Keyframes, Landmarks

if TYPE_CHECKING:
    from services.backend.estimator import WindowedVioEstimator

log = logging.getLogger("sigmaslam.loop")


def corrected_state(msg: EstimatorState, T: np.ndarray) -> EstimatorState:
    """``msg`` moved by the rigid correction T (= T_W'W): pose, velocity and the covariance's p/v blocks."""
    R = T[:3, :3]
    J = np.eye(15)
    J[3:6, 3:6] = J[6:9, 6:9] = R
    return EstimatorState(header=msg.header, T_WS=T @ msg.T_WS, v_W=R @ msg.v_W, gyro_bias=msg.gyro_bias,
                          acc_bias=msg.acc_bias, covariance=J @ msg.covariance @ J.T, status=msg.status)


class PublishedFrame:
    """The frame W' the back end publishes in, as the loop closer moved it: the correction T_W'W applied to the
    last state and the keyframe poses the last ``Keyframes`` messages carried. The occupancy terms' submap
    anchoring (services/backend/protocols.py: SubmapAnchoring), since the mapping's submap poses and the depth poses
    live in that frame.

    ``window``: the estimator, read when a submap is anchored; a provider rather than the estimator itself, since
    this is made before the estimator (whose extra factors, the occupancy terms, need this)."""

    def __init__(self, history: KeyframeHistory, window: Callable[[], WindowedVioEstimator], correct_state: bool,
                 anchor_tolerance_ms: float) -> None:
        self.history, self.window = history, window
        self.correct_state, self.anchor_tolerance_ms = correct_state, anchor_tolerance_ms
        self.T_last = np.eye(4)  # the correction applied to the last state
        self.keyframe_poses: dict[int, np.ndarray] = {}  # keyframe state -> its pose in the last Keyframes message

    def anchor_of(self, stamp_ns: int, T_WM: np.ndarray) -> tuple[int, np.ndarray] | None:
        """The keyframe a submap created at ``stamp_ns`` with pose ``T_WM`` (as the mapping has it now) follows:
        the keyframe nearest its creation within ``o2p.anchor_tolerance_ms`` (state index) and ``T_KM``, taken
        against that keyframe's pose as it was last published (the frame the mapping's T_WM lives in): the pose of
        the last ``Keyframes`` message that carried it, not a newer correction the mapping has not seen yet."""
        tol = self.anchor_tolerance_ms * 1e6
        est = self.window()
        best: tuple[float, int, np.ndarray] | None = None
        for n in est.keyframes:  # still in the window
            if est.values.exists(X(n)) and abs(est.stamps[n] - stamp_ns) <= tol:
                if best is None or abs(est.stamps[n] - stamp_ns) < best[0]:
                    best = (abs(est.stamps[n] - stamp_ns), n, est.values.atPose3(X(n)).matrix())
        for r in reversed(self.history.records):  # marginalised, time order
            if r.stamp_ns < stamp_ns - tol:
                break
            if abs(r.stamp_ns - stamp_ns) <= tol and (best is None or abs(r.stamp_ns - stamp_ns) < best[0]):
                best = (abs(r.stamp_ns - stamp_ns), r.state, r.T_WS)
        if best is None:
            return None
        _, n, T_WK = best
        if self.correct_state:  # as published; never published (yet): moved by the last state's correction
            T_WK = self.keyframe_poses.get(n, self.T_last @ T_WK)
        return n, inv_T(T_WK) @ np.asarray(T_WM, float)

    def correction(self) -> np.ndarray | None:
        """T_W'W applied to the last published state (None without ``loop.correct_state``: W' = W)."""
        return self.T_last.copy() if self.correct_state else None

    def note_published(self, kfs: Keyframes) -> None:
        """Remember the keyframe poses a ``Keyframes`` message carries (:meth:`anchor_of` reads them)."""
        for n, T in zip(np.asarray(kfs.ids), np.asarray(kfs.T_WS)):
            self.keyframe_poses[int(n)] = T


class LoopClosingBackend:
    """``shell`` (services/backend/node.py: BackendShell) with loop closure: ``history`` is the shell's estimator's
    marginalisation listener and feeds ``runner``; ``published`` is the shell's occupancy terms' anchoring."""

    def __init__(self, shell, cfg: LoopConfig, history: KeyframeHistory, runner: ThreadedLoopCloser,
                 published: PublishedFrame) -> None:
        self.shell, self.cfg = shell, cfg
        self.history, self.runner, self.published = history, runner, published
        self._stamps: list[int] = []
        self._T_pub: list[np.ndarray] = []
        self._frame_ids: list[str] = []  # the frame each published pose is in (header.frame_id)
        # stamp -> the back end's solve of a frame it took (a keyframe), corrected as the published states are: the
        # pose the fast path's next frames were solved against; the published state at that stamp is the fast path's
        self._kf_anchor: dict[int, np.ndarray] = {}
        self._generation = 0
        self.dropped_features = 0
        self._end_ns: int | None = None
        self._finished = False
        self._last_process = time.monotonic()
        self._last_save_ns: int | None = None
        self.session = {}  # what the saved map says about this run (source, start time)
        # where this run's sparse map goes (None: nowhere: no loop.map_output, or loop.localise_only)
        self._map_file = (run_map_dir(cfg.map_output) / SPARSE_FILE
                          if cfg.map_output and not cfg.localise_only else None)

    @property
    def frame_id(self) -> str:
        """The frame of the published poses: 'W', or :data:`UNALIGNED_FRAME` while a run localising in a saved map
        has not relocalised yet."""
        return "W" if self.runner.aligned else UNALIGNED_FRAME

    def _save_due(self, stamp_ns: int) -> None:
        """Checkpoint the sparse map every ``loop.map_checkpoint_period_s`` of sensor time (``loop.map_output``)."""
        period_s = self.cfg.map_checkpoint_period_s
        if self._map_file is None or period_s <= 0:
            return
        if self._last_save_ns is None:
            self._last_save_ns = stamp_ns
        elif stamp_ns - self._last_save_ns >= period_s * 1e9:
            self._last_save_ns = stamp_ns
            self.runner.submit_save(self._map_file, self.session, self._window_records())

    def _window_records(self) -> list:
        """The keyframes still in the estimator's window, for the saved map: without them a checkpoint would lag
        the drone by the window's span (8 keyframes, ~3-4 s), and a back end restarted in flight would look for
        itself in a map that ends where it was seconds before (tests/test_reliability_faults.py)."""
        est = self.shell.estimator
        return self.history.capture_window(est) if len(est.keyframes) else []

    def save_map(self) -> bool:
        """Write the sparse map now and wait for it (the end of a run); False when not configured or not written."""
        if self._map_file is None:
            return False
        before = self.runner.saved
        self.runner.submit_save(self._map_file, self.session, self._window_records())
        self.runner.drain()
        return self.runner.saved > before

    @property
    def counts(self) -> dict[str, int]:
        return dict(self.runner.closer.counts)

    def add_keyframe_features(self, msg: KeyframeFeatures) -> None:
        n = len(msg.landmark_ids)
        if n == 0 or np.asarray(msg.descriptors).shape != (n, 32):
            self.dropped_features += 1
            return
        self.runner.submit_features(int(msg.header.stamp_ns), FeatureSet(
            np.asarray(msg.landmark_ids, np.int64), np.asarray(msg.camera_index, np.int64),
            np.asarray(msg.uv, float), np.asarray(msg.descriptors, np.uint8)))

    def process(self, frame):
        """As ``BackendShell.process`` (a frame the estimator wants: services/backend/node.py), with the keyframe
        poses corrected; the state stays in W (the fast path corrects the published ones by
        :meth:`PublishedFrame.correction`). The published states of all frames come in through :meth:`record_state`."""
        self._last_process = time.monotonic()
        if self.shell.o2p is not None:  # map-to-map terms of submaps closed since the last frame
            for term in self.shell.o2p.pop_map_to_map():
                self.runner.submit_map_to_map(term)
            for lp in self.runner.take_verified():  # a revisit: the keyframe co-observes the old landmarks
                if lp.observations:
                    self.shell.o2p.note_loop(lp.query_stamp_ns, lp.observations[2])
        msgs = self.shell.process(frame)
        if msgs is None or msgs[0].status in ("initialising", "reset"):
            return msgs
        state, kfs = msgs
        self._save_due(int(state.header.stamp_ns))
        if kfs is not None and self.cfg.early_loops:
            self.runner.submit_window(kfs.stamps_ns, kfs.T_WS)
        if (frame_id := self.frame_id) != state.header.frame_id:
            state = dataclasses.replace(state, header=dataclasses.replace(state.header, frame_id=frame_id))
            msgs = state, kfs
        if not self.cfg.correct_state:
            self._note_anchor(state, np.eye(4))
            return msgs
        T, gen, (g_ids, g_stamps, g_T) = self.runner.snapshot()  # correction and keyframes from the same solve
        self.published.T_last = T  # the fast path applies it to the states (estimator/window's T_corr)
        self._note_anchor(state, T)
        if kfs is not None:
            ids, stamps, poses = kfs.ids, kfs.stamps_ns, np.einsum("ij,njk->nik", T, kfs.T_WS)
            if gen != self._generation:  # the correction moved the past keyframes: send them all once
                self._generation = gen
                keep = ~np.isin(g_ids, ids)
                ids, stamps = np.r_[g_ids[keep], ids], np.r_[g_stamps[keep], stamps]
                poses = np.concatenate([g_T[keep], poses])
            kfs = Keyframes(header=dataclasses.replace(kfs.header, frame_id=state.header.frame_id),
                            ids=np.asarray(ids, np.int64), stamps_ns=np.asarray(stamps, np.int64),
                            T_WS=np.ascontiguousarray(poses, np.float64))
            self.published.note_published(kfs)
        return state, kfs

    def _note_anchor(self, state: EstimatorState, T: np.ndarray) -> None:
        """Keep the back end's pose of the frame of ``state`` (moved by the correction ``T`` the published states
        get): the anchor the fast path's next frames are solved against (estimator/window), see :meth:`_follow`."""
        self._kf_anchor[int(state.header.stamp_ns)] = T @ np.asarray(state.T_WS, float)

    def record_state(self, state: EstimatorState) -> None:
        """A published causal state (estimator/state, in W'): the frames the final trajectory is given for, and
        the tracking status the loop closer follows."""
        if state.status in ("initialising", "reset"):
            return
        stamp = int(state.header.stamp_ns)
        if self._stamps and stamp <= self._stamps[-1]:
            return
        self._stamps.append(stamp)
        self._T_pub.append(np.array(state.T_WS))
        self._frame_ids.append(state.header.frame_id)
        # the pose only matters until a saved map's frame is reached (the closer aligns the session with it)
        self.runner.submit_status(stamp, state.status, None if self.runner.aligned else np.array(state.T_WS))

    def take_landmarks(self) -> Landmarks | None:
        """As ``BackendShell.take_landmarks``, moved by the correction applied to the last state."""
        msg = self.shell.take_landmarks()
        if msg is None or not self.cfg.correct_state:
            return msg
        T = self.published.T_last
        return Landmarks(header=msg.header, ids=msg.ids, p_W=msg.p_W @ T[:3, :3].T + T[:3, 3],
                         num_observations=msg.num_observations, last_seen_ns=msg.last_seen_ns)

    def finish(self, seq: int = 0) -> FinalTrajectory | None:
        """Final bundle adjustment over every keyframe (None when too little was tracked)."""
        self.runner.drain()
        est = self.shell.estimator
        window = self.history.capture_window(est)
        records = self.history.records + window
        closer = self.runner.closer
        late_loops, late_obs = closer.pending_for_final(window)
        c = closer.counts
        if len(records) < 2 or len(self._stamps) < 2:
            return None
        stamps = np.array(self._stamps, np.int64)
        T_pub = np.array(self._T_pub)
        if self.cfg.final_ba:
            loops = closer.loops + late_loops
            anchors, T_init = [], None
            if closer.prior is not None and closer.aligned:  # in the saved map's frame: its matches place the run
                T_init = closer.correction()
                anchors = [(new, closer.graph.estimate[old] @ T, cov) for old, new, T, cov in loops
                           if old in closer.graph.fixed]
            res = bundle_adjust(records, est.cameras_in_use(), est.cfg.sigma_px, est.cfg.cauchy_k, loops,
                                self.cfg.final_ba_iterations, loop_observations=closer.loop_observations + late_obs,
                                map_to_map=closer.map_to_map_for_final(), anchors=anchors, T_init=T_init,
                                merge_loop_landmarks=self.cfg.final_ba_merge_landmarks,
                                prune_ratio=self.cfg.final_ba_prune_ratio)
            T_final = self._follow(stamps, T_pub, res.stamps_ns, res.T_WS)
            n_kf = len(res.stamps_ns)
            log.info("final BA: %d keyframes, %d landmarks (%d merged through loops, %d badly fitting dropped), %d "
                     "observations, %d map-to-map, error %.1f -> %.1f", n_kf, res.landmarks, res.merged, res.pruned,
                     res.observations, res.map_to_map, res.initial_error, res.final_error)
        else:  # the pose graph alone
            g_ids, g_stamps, g_T = closer.corrected_keyframes()
            T_final = self._follow(stamps, T_pub, g_stamps, g_T) if len(g_ids) else T_pub
            n_kf = len(g_ids)
        return FinalTrajectory(header=Header(stamp_ns=int(stamps[-1]), seq=seq, frame_id=self.frame_id), stamps_ns=stamps,
                               T_WS=np.ascontiguousarray(T_final, np.float64), keyframes=int(n_kf),
                               loops_proposed=int(c["proposed"]), loops_verified=int(c["verified"]),
                               loops_accepted=int(c["accepted"]), relocalisations=int(c["relocalised"]))

    def _follow(self, stamps: np.ndarray, T_pub: np.ndarray, kf_stamps: np.ndarray, kf_T: np.ndarray) -> np.ndarray:
        """:func:`follow_keyframes` per published frame: a frame follows a keyframe published in the same frame (a
        run that relocalised in a saved map published its first poses in another), so no pose is moved by a
        correction taken in the other frame."""
        # the published state at a keyframe is the fast path's (solved before the window was); the frames after it
        # were solved against the window's pose of it (a young window's fast path was 6 cm off at V2_01's second
        # keyframe, which the window then solved right); the back end's first keyframe has no published state
        # ('initialising') but its pose anchors the frames up to the second
        anchor = np.array([self._kf_anchor.get(int(s), np.full((4, 4), np.nan)) for s in kf_stamps]).reshape(-1, 4, 4)
        ids = np.array(self._frame_ids[:len(stamps)])
        if len(set(ids.tolist())) <= 1:
            return follow_keyframes(stamps, T_pub, kf_stamps, kf_T, anchor)
        out = np.array(T_pub, float)
        for f in set(ids.tolist()):
            sel = ids == f
            kf = np.isin(kf_stamps, stamps[sel])
            if kf.any():
                out[sel] = follow_keyframes(stamps[sel], T_pub[sel], kf_stamps[kf], kf_T[kf], anchor[kf])
        return out

    def poll_end(self, stream_ends, idle_s: float = 2.0) -> FinalTrajectory | None:
        """Call while no frame is waiting, with the StreamEnd messages received since the last call: returns the
        final trajectory once, when the player's stream has ended and its last frame is processed (or no frame
        came for ``idle_s`` after the end)."""
        for e in stream_ends:
            if e.source == "player":
                self._end_ns = int(e.header.stamp_ns)
        if self._finished or self._end_ns is None:
            return None
        last = self._stamps[-1] if self._stamps else -1
        if last < self._end_ns and time.monotonic() - self._last_process < idle_s:
            return None
        self._finished = True
        t0 = time.perf_counter()
        if self.save_map():
            log.info("sparse map saved to %s", self._map_file)
        try:
            out = self.finish()
        except (RuntimeError, ValueError) as exc:
            log.warning("final trajectory not computed: %s", exc)
            return None
        log.info("final trajectory in %.1f s; loops %s", time.perf_counter() - t0, self.counts)
        return out

    def close(self) -> None:
        if not self._finished and self.save_map():  # stopped before the stream ended: keep what was mapped
            log.info("sparse map saved to %s at exit", self._map_file)
        self.runner.close()
