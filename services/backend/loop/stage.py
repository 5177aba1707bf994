"""Loop closure as a stage of the back end (:class:`LoopClosure`; no transport in here).

Built by the back end's composition root (services/backend/compose.py) from parts made before the estimator: the
keyframe history (the estimator's marginalisation listener), the :class:`ThreadedLoopCloser` it feeds and the
:class:`PublishedFrame`. The back-end node calls it around each frame the window takes:

* the estimator's per-frame path only enqueues, so ``estimator/window`` is never delayed by verification or
  pose-graph solves;
* :meth:`LoopClosure.after_frame` corrects the keyframe poses by the pose graph's latest correction ``T_W'W``
  (when ``loop.correct_state``; the fast path applies the same correction to the published states); after a solve
  the keyframes message also carries every corrected pose-graph node;
* with occupancy-to-point factors on, the :class:`PublishedFrame` is their submap anchoring, the map-to-map terms
  come in through :meth:`LoopClosure.add_map_to_map` and the verified revisits go back to them
  (:meth:`LoopClosure.take_revisits`);
* keeps the published causal poses (:meth:`LoopClosure.record_state`), and at the end of the stream
  (:meth:`LoopClosure.finish`) runs the final bundle adjustment over all keyframes with IMU, loop and map-to-map
  factors, giving the non-causal trajectory.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np

from services.backend.loop.config import LoopConfig
from services.backend.loop.final_ba import bundle_adjust, follow_keyframes
from services.backend.loop.history import KeyframeHistory
from services.backend.loop.loop_thread import ThreadedLoopCloser
from services.backend.loop.published_frame import PublishedFrame
from services.backend.loop.verification import FeatureSet
from services.backend.window.estimator import WindowedVioEstimator
from shared.map_folder import SPARSE_FILE, UNALIGNED_FRAME, run_map_dir
from shared.messages import EstimatorState, FinalTrajectory, Header, KeyframeFeatures, Keyframes, Landmarks

log = logging.getLogger("sigmaslam.loop")


class LoopClosure:
    """Loop closure around the window of ``estimator``: ``history`` is its marginalisation listener and feeds
    ``runner``; ``published`` is the frame the back end publishes in (the occupancy terms' anchoring); ``session``:
    what the saved map says about this run (source, start time)."""

    def __init__(self, cfg: LoopConfig, estimator: WindowedVioEstimator, history: KeyframeHistory,
                 runner: ThreadedLoopCloser, published: PublishedFrame, session: dict | None = None) -> None:
        self.cfg, self.estimator = cfg, estimator
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
        self.session = session or {}
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
        est = self.estimator
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

    def before_frame(self) -> None:
        """A frame the window takes is about to be processed (the end of the stream waits for the last one)."""
        self._last_process = time.monotonic()

    def add_map_to_map(self, term) -> None:
        """A map-to-map term of a closed submap (services/backend/o2p/map_to_map.py) for the pose graph."""
        self.runner.submit_map_to_map(term)

    def take_revisits(self) -> list[tuple[int, np.ndarray]]:
        """(keyframe stamp, the old landmark ids its verified loop matched) of the loops verified since the last
        call: a revisit co-observes the old landmarks."""
        return [(lp.query_stamp_ns, lp.observations[2]) for lp in self.runner.take_verified() if lp.observations]

    def after_frame(self, msgs: tuple[EstimatorState, Keyframes | None] | None
                    ) -> tuple[EstimatorState, Keyframes | None] | None:
        """The window's messages of a frame with the keyframe poses corrected; the state stays in W (the fast path
        corrects the published ones by :meth:`correction`). The published states of all frames come in through
        :meth:`record_state`."""
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
        self._kf_anchor[int(state.header.stamp_ns)] = (T @ np.asarray(state.T_WS, float), state.header.frame_id)

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

    def correction(self) -> np.ndarray | None:
        """T_W'W applied to the last published state (None without ``loop.correct_state``: W' = W)."""
        return self.published.correction()

    def correct_landmarks(self, msg: Landmarks) -> Landmarks:
        """The window's landmarks moved by the correction applied to the last state."""
        if not self.cfg.correct_state:
            return msg
        T = self.published.T_last
        return Landmarks(header=msg.header, ids=msg.ids, p_W=msg.p_W @ T[:3, :3].T + T[:3, 3],
                         num_observations=msg.num_observations, last_seen_ns=msg.last_seen_ns)

    def finish(self, seq: int = 0) -> FinalTrajectory | None:
        """Final bundle adjustment over every keyframe (None when too little was tracked)."""
        self.runner.drain()
        est = self.estimator
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
        ids = np.array(self._frame_ids[:len(stamps)])
        if len(set(ids.tolist())) <= 1:
            return follow_keyframes(stamps, T_pub, kf_stamps, kf_T, self._anchors(kf_stamps, ids[0] if len(ids) else ""))
        out = np.array(T_pub, float)
        for f in set(ids.tolist()):
            sel = ids == f
            kf = np.isin(kf_stamps, stamps[sel])
            if kf.any():
                out[sel] = follow_keyframes(stamps[sel], T_pub[sel], kf_stamps[kf], kf_T[kf],
                                            self._anchors(kf_stamps[kf], f))
        return out

    def _anchors(self, kf_stamps: np.ndarray, frame_id: str) -> np.ndarray:
        """The anchors (K,4,4) of these keyframes that were taken in ``frame_id`` (NaN otherwise): the window may
        solve a keyframe after the run relocalised in a saved map although its frame was published before, in the
        run's own frame; an anchor in the map's frame would move those frames by the map's offset."""
        nan = np.full((4, 4), np.nan)
        out = [a if f == frame_id else nan for a, f in (self._kf_anchor.get(int(s), (nan, frame_id)) for s in kf_stamps)]
        return np.array(out).reshape(-1, 4, 4)

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
