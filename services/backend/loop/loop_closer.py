"""Loop closing for the windowed estimator: keyframe features in, loop constraints and a pose correction out.

Inputs (in time order): the features of each new keyframe (:meth:`LoopCloser.add_keyframe_features`, from
the frontend), the records of keyframes leaving the window (:meth:`LoopCloser.add_record`, from the
estimator's marginalisation hook) and the tracking status (:meth:`LoopCloser.note_status`).

* A new keyframe's bag is scored against the *marginalised* keyframes (they carry 3D landmarks) older than
  ``min_age_s``; the best candidates are verified by PnP against the landmarks of the old keyframe and of its
  ``verify_neighbours`` stored neighbours on each side (:meth:`LoopCloser.verification_set`); a PnP pose with at
  least ``guided_seed_inliers`` inliers is expanded by guided matching against ``guided_neighbours`` on each side
  (services/backend/loop/verification.py). Counts: proposed (candidates), guided (poses expanded), verified (PnP
  accepted), accepted (loop factor added).
* A verified loop waits until the query keyframe leaves the window itself, then enters the pose graph as a
  relative-pose factor between the two nodes; the graph is solved and the correction ``T_W'W`` (window
  frame to corrected frame at the newest node) is updated.
* Map-to-map occupancy-to-point terms (:meth:`LoopCloser.add_map_to_map`, from the back end's o2p terms)
  wait until the keyframes anchoring both submaps are pose-graph nodes, then join the graph like loops.
* Relocalisation: after ``relocalise_after_s`` without tracking, the next keyframes are queried against the
  keyframes from before the loss regardless of age, so the trajectory after the gap is tied back to the map.
* A saved map (:meth:`LoopCloser.load_prior`, services/backend/loop/saved_map.py): its keyframes join the database
  and the pose graph as fixed nodes in the map's frame. Until the session is aligned to the map, each keyframe is
  queried against the map's keyframes alone (any age); a verified match proposes T_map_window, and once
  ``loop.relocalise_confirmations`` of them agree the session's nodes are moved into the map's frame and the matches
  join the graph as loops (:attr:`LoopCloser.aligned`). From then on the published poses are in the map's frame, and
  later matches to the map are ordinary loops to fixed nodes. :meth:`LoopCloser.sparse_map` gives the map to save:
  the saved map's keyframes, unchanged, and this session's aligned keyframes.

:class:`services.backend.loop.loop_thread.ThreadedLoopCloser` runs all of this in a thread of its own: the
caller only enqueues.
"""

from __future__ import annotations

import bisect
import collections
import logging
import time
from dataclasses import dataclass

import numpy as np

from services.backend.loop.config import LoopConfig
from services.backend.loop.covisibility import Covisibility
from services.backend.loop.history import KeyframeRecord
from services.backend.loop.map_localiser import MapLocaliser
from services.backend.loop.map_session import SavedMapSession
from services.backend.loop.place_recognition import PlaceDatabase
from services.backend.loop.pose_graph import LoopConstraint, PoseGraph
from services.backend.loop.saved_map import SparseMap, vocabulary_id
from services.backend.loop.verification import FeatureSet, Guide, normalised_xy, verify_pnp
from services.backend.loop.vocabulary import DEFAULT_PATH, Vocabulary, l1_score
from shared.geometry import inv_T

log = logging.getLogger("sigmaslam.loop")



@dataclass(frozen=True)
class VerifiedLoop:
    old_state: int
    query_stamp_ns: int
    T_WS_query: np.ndarray  # query body pose in the old keyframe's (window-at-the-time) frame
    covariance: np.ndarray
    inliers: int
    relocalisation: bool
    # (camera (I,), normalised xy (I,2), old landmark ids (I,), the query features' own landmark ids (I,)) of the
    # PnP inliers
    observations: tuple = ()


class LoopCloser(SavedMapSession):
    def __init__(self, cfg: LoopConfig, cameras, vocabulary: Vocabulary | None = None) -> None:
        self.cfg = cfg
        self.voc = vocabulary or Vocabulary.load(cfg.vocabulary or DEFAULT_PATH)
        self.voc_id = vocabulary_id(self.voc)
        self.db = PlaceDatabase(self.voc.size)
        self.graph = PoseGraph(loop_cauchy_k=cfg.loop_cauchy_k, attitude_sigma_rad=np.deg2rad(cfg.attitude_sigma_deg))
        self.covisibility = Covisibility()
        self._undistort = [c.undistort for c in cameras]
        self._T_SC = np.array([c.T_SC for c in cameras])
        self._focal = np.array([c.focal_px for c in cameras], float)
        self._features: dict[int, tuple[FeatureSet, np.ndarray]] = {}  # stamp -> (features, bag), not yet marginalised
        self._old: dict[int, tuple[FeatureSet, np.ndarray, KeyframeRecord]] = {}  # state -> (features, p_W, record)
        self._old_keys: list[int] = []  # the keys of _old, sorted (a saved map's after this session's)
        self._prev_record: KeyframeRecord | None = None
        self._prev_bag: np.ndarray | None = None
        self._pending: list[VerifiedLoop] = []
        self._early: set[int] = set()  # query stamps of pending loops already in the graph (loop.early_loops)
        self._now_ns = -(1 << 62)  # the newest sensor time seen (states, windows)
        self.loop_delays_s: list[float] = []  # per loop factor: sensor time from its query keyframe to the graph
        self.loops: list[tuple[int, int, np.ndarray, np.ndarray]] = []  # (old state, new state, T_old_new, cov)
        # (state, camera, xy, old landmark, the query feature's own landmark): the final BA's loop observations
        self.loop_observations: list[tuple[int, int, np.ndarray, int, int]] = []
        self.counts = collections.Counter()
        self._lost_since: int | None = None
        self._reloc_before: int | None = None  # relocalisation mode: candidates older than this stamp
        self.solve_ms: list[float] = []
        self.node_stamps: dict[int, int] = {}
        self._dirty = False
        self._last_solve_ns = -(1 << 62)
        self._m2m_pending: list = []  # map-to-map terms waiting for their anchor keyframes to become nodes
        self.max_pending_map_to_map = 100
        self.prior: SparseMap | None = None  # a saved map this session localises in (load_prior)
        self._localiser: MapLocaliser | None = None  # until the session is in the saved map's frame
        self.aligned_at_ns: int | None = None  # stamp of the keyframe whose match aligned it to the saved map

    @property
    def aligned(self) -> bool:
        """Whether the session's frame is the saved map's (always, without a saved map)."""
        return self._localiser is None

    # ------------------------------------------------------------------ status
    def note_status(self, stamp_ns: int, status: str, T_pub: np.ndarray | None = None) -> None:
        """The fast path's published state at ``stamp_ns``: its status and, while a saved map's frame is not yet
        reached, its pose ``T_pub`` (published frame: this closer's correction applied to the window's pose), with
        which a keyframe's match to the map aligns the session at once, without waiting for the keyframe to leave
        the window."""
        self._now_ns = max(self._now_ns, int(stamp_ns))
        if self._localiser is not None:
            T_W = None if T_pub is None else inv_T(self.correction()) @ np.asarray(T_pub, float)  # window pose
            self._align(self._localiser.note_state(stamp_ns, status, T_W), stamp_ns)
        if status == "tracking":
            if self._lost_since is not None and stamp_ns - self._lost_since >= self.cfg.relocalise_after_s * 1e9:
                self._reloc_before = self._lost_since
                self.counts["losses"] += 1
            self._lost_since = None
        elif status in ("imu_only", "lost") and self._lost_since is None:
            self._lost_since = int(stamp_ns)

    @property
    def relocalising(self) -> bool:
        return self._reloc_before is not None

    # ------------------------------------------------------------------ keyframe features
    def add_keyframe_features(self, stamp_ns: int, fs: FeatureSet) -> list[VerifiedLoop]:
        cfg = self.cfg
        bag = self.voc.bag(fs.descriptors)
        self._features[int(stamp_ns)] = (fs, bag)
        ref = float(l1_score(bag, self._prev_bag)) if self._prev_bag is not None else None
        self._prev_bag = bag
        reloc = self._reloc_before is not None
        if not self.aligned:  # not yet in the saved map's frame: only the map's keyframes can place it there
            cands = [c for c in self.db.query(bag, stamp_ns, 0.0, cfg.min_score, 0.0, ref, 3 * cfg.max_candidates)
                     if self._is_prior(c.key)]
        else:
            min_age = 0.0 if reloc else cfg.min_age_s
            cands = self.db.query(bag, stamp_ns, min_age, cfg.min_score, 0.0 if reloc else cfg.min_normalised,
                                  ref, max_candidates=cfg.max_candidates if not reloc else 3 * cfg.max_candidates)
            if reloc:
                cands = [c for c in cands if c.stamp_ns < self._reloc_before]
        out = []
        for c in cands:
            self.counts["proposed"] += 1
            old_fs, old_p = self.verification_set(c.key)
            guide = None
            if cfg.guided_seed_inliers > 0:  # the wider set is gathered only if RANSAC gives a seed
                guide = Guide(seed_inliers=cfg.guided_seed_inliers, radius_px=cfg.guided_radius_px,
                              load=lambda key=c.key: self.verification_set(key, cfg.guided_neighbours))
            res = verify_pnp(fs, old_fs, old_p, self._undistort, self._T_SC, self._focal, cfg.sigma_px,
                             cfg.max_hamming, cfg.ransac_px, cfg.min_inliers, cfg.min_inlier_ratio, cfg.cov_inflation,
                             guide)
            if res.expanded:
                self.counts["guided"] += 1
                old_fs = guide.features
            if not res.accepted:
                self.counts["rejected_pnp"] += 1
                continue
            self.counts["verified"] += 1
            cams = np.asarray(fs.camera_index, np.int64)[res.query_index]
            xy = normalised_xy(fs, self._undistort, res.query_index)
            # a saved map's landmark ids are another session's: its matches give no observations of this one's
            obs = () if self._is_prior(c.key) else (cams, xy, np.asarray(old_fs.landmark_ids, np.int64)[res.old_index],
                                                    np.asarray(fs.landmark_ids, np.int64)[res.query_index])
            loop = VerifiedLoop(c.key, int(stamp_ns), res.T_WS, res.covariance, res.inliers, reloc, obs)
            self._pending.append(loop)
            out.append(loop)
            if self._localiser is not None:  # a match to the map (the only candidates): align when it can
                self._align(self._localiser.note_match(stamp_ns, loop), stamp_ns)
            log.info("loop verified: keyframe at %d ns sees state %d (%d inliers%s)", stamp_ns, c.key, res.inliers,
                     ", relocalisation" if reloc else "")
            break  # one verified loop per query keyframe is enough
        if out and reloc:
            self._reloc_before = None
            self.counts["relocalised"] += 1
        # drop features of keyframes the estimator never made keyframes (bounded memory)
        while len(self._features) > 200:
            self._features.pop(next(iter(self._features)))
        return out

    def _landmarks_seen(self, fs: FeatureSet, rec: KeyframeRecord) -> np.ndarray | None:
        """The positions (n,3) of the landmarks of ``fs`` as ``rec`` has them (NaN where unknown); None when fewer
        than ``loop.min_inliers`` are known (too few to verify a loop against)."""
        p_W = np.array([rec.landmarks.get(int(i), (np.nan,) * 3) for i in fs.landmark_ids], float).reshape(-1, 3)
        return p_W if np.isfinite(p_W[:, 0]).sum() >= self.cfg.min_inliers else None

    def _store_old(self, key: int, fs: FeatureSet, p_W: np.ndarray, rec: KeyframeRecord) -> None:
        if key not in self._old:
            bisect.insort(self._old_keys, key)
        self._old[key] = (fs, p_W, rec)

    def verification_set(self, key: int, neighbours: int | None = None) -> tuple[FeatureSet, np.ndarray]:
        """What a candidate ``key`` is verified against: the features with a known landmark position of the stored
        keyframe ``key`` and of up to ``neighbours`` (default ``loop.verify_neighbours``) stored keyframes on each
        side of it (of the same session, or of the same saved map), one feature per landmark, the candidate's own
        first. All positions are in the window's world frame, each as the window had it when its keyframe left
        (neighbours leave a few keyframes apart; around a tracking loss the window may drift between them, which is
        one reason the inlier threshold stays at 25). Returns (features, p_W (K,3))."""
        i = bisect.bisect_left(self._old_keys, key)
        n = self.cfg.verify_neighbours if neighbours is None else neighbours
        near = [k for k in self._old_keys[max(0, i - n):i + n + 1] if k != key and self._is_prior(k) == self._is_prior(key)]
        sets = [self._old[k] for k in [key, *sorted(near, key=lambda k: abs(k - key))]]
        fs = [s[0] for s in sets]
        ids = np.concatenate([f.landmark_ids for f in fs]).astype(np.int64)
        p_W = np.concatenate([s[1] for s in sets]).reshape(-1, 3)
        known = np.flatnonzero(np.isfinite(p_W).all(1))
        _, first = np.unique(ids[known], return_index=True)  # index of each landmark's first occurrence
        keep = known[np.sort(first)]
        cat = lambda attr: np.concatenate([getattr(f, attr) for f in fs])[keep]  # noqa: E731
        return FeatureSet(ids[keep], cat("camera_index"), cat("uv"), cat("descriptors")), p_W[keep]

    # ------------------------------------------------------------------ marginalised keyframes
    def add_record(self, rec: KeyframeRecord) -> bool:
        """A keyframe left the window: pose-graph node, database entry, pending loops. True when solved."""
        prev = self._prev_record
        self.node_stamps[rec.state] = rec.stamp_ns
        if prev is None:
            self.graph.add_node(rec.state, rec.T_WS)
        else:
            linked = prev.next_state == rec.state and prev.rel_cov_to_next is not None
            cov = prev.rel_cov_to_next if linked else np.diag([1e-2] * 3 + [1.0] * 3)
            T_rel = inv_T(prev.T_WS) @ prev.T_WS_next if linked and prev.T_WS_next is not None else None
            self.counts["unlinked_nodes"] += int(not linked)
            self.graph.add_node(rec.state, rec.T_WS, cov, T_rel)
        self._prev_record = rec
        self.covisibility.add_keyframe(rec.state, np.fromiter(rec.obs.keys(), np.int64, len(rec.obs)))
        feats = self._features.pop(rec.stamp_ns, None)
        for s in [s for s in self._features if s < rec.stamp_ns]:
            self._features.pop(s)
        if feats is not None:
            fs, bag = feats
            p_W = self._landmarks_seen(fs, rec)
            if p_W is not None:
                self._store_old(rec.state, fs, p_W, rec)
                self.db.add(rec.state, rec.stamp_ns, bag)
        self._add_ready_map_to_map()
        solved = self._solve_if_due(rec.stamp_ns)
        keep = []
        for lp in self._pending:
            if lp.query_stamp_ns == rec.stamp_ns:
                solved |= self._accept(lp, rec)
            elif lp.query_stamp_ns > rec.stamp_ns:
                keep.append(lp)
            else:
                self.counts["loops_without_keyframe"] += 1
        self._pending = keep
        self._early &= {lp.query_stamp_ns for lp in keep}  # only pending loops can be early ones
        return solved

    def note_window(self, stamps_ns: np.ndarray, T_WS: np.ndarray) -> bool:
        """The window's keyframe poses (W, uncorrected) after an optimisation (``loop.early_loops``). A pending loop
        whose query keyframe is among them joins the graph now, between its old node and the newest node: the
        window's relative pose from that node to the query keyframe carries the PnP pose over (a few keyframes of
        odometry, mm). True when the graph was solved."""
        if len(stamps_ns):
            self._now_ns = max(self._now_ns, int(np.max(stamps_ns)))
        if not self.cfg.early_loops or not self._pending or not self.graph.keys or not self.aligned:
            return False
        where = {int(t): np.asarray(T, float) for t, T in zip(stamps_ns, T_WS)}
        newest = self.graph.keys[-1]
        added = False
        for lp in self._pending:
            T_WQ = where.get(lp.query_stamp_ns)
            if T_WQ is None or lp.query_stamp_ns in self._early or self._is_prior(lp.old_state):
                continue
            T_newest_query = inv_T(self.graph.odom[newest]) @ T_WQ
            T_old_newest = inv_T(self._old[lp.old_state][2].T_WS) @ lp.T_WS_query @ inv_T(T_newest_query)
            if self._add_loop_factor(lp.old_state, newest, T_old_newest, lp.covariance, lp.query_stamp_ns):
                self._early.add(lp.query_stamp_ns)
                self.counts["accepted_early"] += 1
                added = True
        return added and self._solve_if_due(self.node_stamps[newest])

    def _add_loop_factor(self, old_state: int, key: int, T_old_key: np.ndarray, cov: np.ndarray,
                         query_stamp_ns: int) -> bool:
        """A loop factor old -> key, unless it moves ``key`` further than ``max_translation_jump_m``."""
        if self.cfg.max_translation_jump_m > 0:
            predicted = self.graph.estimate[old_state] @ T_old_key
            if np.linalg.norm(predicted[:3, 3] - self.graph.estimate[key][:3, 3]) > self.cfg.max_translation_jump_m:
                self.counts["rejected_jump"] += 1
                return False
        self.graph.add_loop(LoopConstraint(old_state, key, T_old_key, cov))
        self.loop_delays_s.append(1e-9 * max(0, self._now_ns - int(query_stamp_ns)))
        self._dirty = True
        return True

    def add_map_to_map(self, term) -> bool:
        """A map-to-map term (services.backend.o2p.terms.MapToMap); joins the graph once both anchor keyframes
        are nodes. True when the graph was solved."""
        self._m2m_pending.append(term)
        while len(self._m2m_pending) > self.max_pending_map_to_map:
            self._m2m_pending.pop(0)
            self.counts["map_to_map_dropped"] += 1
        self._add_ready_map_to_map()
        return self._solve_if_due(self.node_stamps[self.graph.keys[-1]]) if self.graph.keys else False

    def _add_ready_map_to_map(self) -> None:
        keep = []
        for t in self._m2m_pending:
            if t.state_m not in self.graph.odom or t.state_o not in self.graph.odom:
                keep.append(t)
            elif self.graph.add_map_to_map(t):
                self.counts["map_to_map_accepted"] += 1
                self._dirty = True
            else:  # map_to_map_too_few_inside (no overlap at the graph's estimate) or map_to_map_chi2
                self.counts[f"map_to_map_{self.graph.last_map_to_map_reason}"] += 1
        self._m2m_pending = keep

    def map_to_map_for_final(self) -> list:
        """Map-to-map terms of the pose graph and those still waiting (anchors in the window at the end)."""
        return list(self.graph.map_to_map) + list(self._m2m_pending)

    def _accept(self, lp: VerifiedLoop, rec: KeyframeRecord) -> bool:
        old = self._old[lp.old_state][2]
        T_old_new = inv_T(old.T_WS) @ lp.T_WS_query
        if not self.aligned:
            return self._try_align(lp, rec, T_old_new) if self._is_prior(lp.old_state) else False
        early = lp.query_stamp_ns in self._early  # in the graph already (note_window): the final BA's loop only
        if not early and not self._add_loop_factor(old.state, rec.state, T_old_new, lp.covariance, lp.query_stamp_ns):
            return False
        self.loops.append((old.state, rec.state, T_old_new, lp.covariance))
        if lp.observations:  # the query keyframe observes the old landmarks: used by the final BA
            self.loop_observations += self._observations_of(rec.state, lp)
        self.counts["accepted"] += 1
        return self._solve_if_due(rec.stamp_ns)

    def _solve_if_due(self, stamp_ns: int) -> bool:
        """Solve the pose graph when loops were added and the last solve is ``min_solve_interval_s`` old (gtsam
        holds Python's GIL while it solves, so solves are rationed to keep the estimator's thread running)."""
        if not self._dirty or stamp_ns - self._last_solve_ns < self.cfg.min_solve_interval_s * 1e9:
            return False
        t0 = time.perf_counter()
        self.graph.optimise(self.cfg.pose_graph_iterations)
        self.solve_ms.append(1e3 * (time.perf_counter() - t0))
        self._dirty = False
        self._last_solve_ns = int(stamp_ns)
        return True

    def pending_for_final(self, window: list[KeyframeRecord]) -> tuple[list, list]:
        """Loops (and their landmark observations) still waiting for a query keyframe that is in ``window`` (the
        keyframes left in the estimator at the end of a run), for the final BA."""
        by_stamp = {r.stamp_ns: r for r in window}
        loops, obs = [], []
        for lp in self._pending:
            rec = by_stamp.get(lp.query_stamp_ns)
            if rec is None or lp.old_state not in self._old:
                continue
            old = self._old[lp.old_state][2]
            loops.append((old.state, rec.state, inv_T(old.T_WS) @ lp.T_WS_query, lp.covariance))
            if lp.observations:
                obs += self._observations_of(rec.state, lp)
        return loops, obs

    @staticmethod
    def _observations_of(state: int, lp: VerifiedLoop) -> list[tuple[int, int, np.ndarray, int, int]]:
        return [(state, int(c), p, int(lm), int(own)) for c, p, lm, own in zip(*lp.observations)]

    def correction(self) -> np.ndarray:
        return self.graph.correction()

    def corrected_keyframes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(states, stamps, corrected T_WS) of every pose-graph node of this session (not a saved map's)."""
        keys = list(self.graph.keys)
        return (np.array(keys, np.int64), np.array([self.node_stamps[k] for k in keys], np.int64),
                np.array([self.graph.estimate[k] for k in keys]).reshape(-1, 4, 4))
