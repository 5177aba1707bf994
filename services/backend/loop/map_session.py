"""The saved-map side of the loop closer (:class:`SavedMapSession`, a base of
:class:`services.backend.loop.loop_closer.LoopCloser`): loading a saved map to localise in, aligning this session with
its frame once matches agree, and the sparse map to save (docs/maps.md). The attributes it reads are the loop
closer's."""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

import numpy as np

from services.backend.loop.history import KeyframeRecord
from services.backend.loop.map_localiser import MapLocaliser
from services.backend.loop.saved_map import LOOP, ODOMETRY, SparseMap, SparseMapError, build_map, concatenate
from services.backend.loop.verification import normalised_xy
from shared.geometry import inv_T, transform_points

if TYPE_CHECKING:
    from services.backend.loop.loop_closer import VerifiedLoop

log = logging.getLogger("sigmaslam.loop")

WINDOW_EDGE_COV = np.diag([1e-4] * 3 + [1e-4] * 3)  # a saved window keyframe's link: ~0.6 deg, 1 cm (1 sigma)
PRIOR_KEY_BASE = 1 << 40  # pose-graph keys of a saved map's keyframes: PRIOR_KEY_BASE + row (never a state index)
PRIOR_STAMP_NS = -(1 << 62)  # their stamp in the place database: older than anything, whatever min_age_s


class SavedMapSession:
    """A saved map's keyframes as fixed pose-graph nodes and database entries, the session's alignment with them, and
    the map this session saves."""

    def load_prior(self, m: SparseMap) -> None:
        """Localise in the saved map ``m``: its keyframes become fixed pose-graph nodes and database entries."""
        if self.graph.keys:
            raise RuntimeError("a saved map must be loaded before the first keyframe")
        voc = m.meta.get("vocabulary")
        if voc and voc != self.voc_id:
            raise SparseMapError(f"the saved map was made with vocabulary {voc}, this back end has {self.voc_id} "
                                 "(loop.vocabulary)")
        for i in range(len(m)):
            key = PRIOR_KEY_BASE + i
            fs, p_W = m.features(i)
            rec = KeyframeRecord(key, int(m.stamps_ns[i]), m.T_WS[i], np.zeros(3), None, {}, {})
            self.graph.add_fixed_node(key, m.T_WS[i])
            self.node_stamps[key] = int(m.stamps_ns[i])
            if len(fs.landmark_ids) and np.isfinite(p_W[:, 0]).sum() >= self.cfg.min_inliers:
                self._store_old(key, fs, np.asarray(p_W, float), rec)
                self.db.add(key, PRIOR_STAMP_NS, self.voc.bag(fs.descriptors))
        self.prior = m
        self._localiser = MapLocaliser(self.cfg, self.counts)
        self.counts["map_keyframes"] = len(m)
        log.info("saved map loaded: %d keyframes, %d in the place database", len(m), len(self.db))

    def _is_prior(self, key: int) -> bool:
        return key >= PRIOR_KEY_BASE

    def _try_align(self, lp: VerifiedLoop, rec: KeyframeRecord, T_old_new: np.ndarray) -> bool:
        """A match of keyframe ``rec`` to the saved map, its keyframe now a node, while not aligned: a guess from the
        node's window pose if its state gave none; a loop if the session is aligned by then."""
        self._align(self._localiser.note_node(rec.stamp_ns, rec.T_WS), rec.stamp_ns)
        return self._accept(lp, rec) if self.aligned else False

    def _align(self, T_map_window: np.ndarray | None, stamp_ns: int) -> None:
        """Move the session into the saved map's frame by ``T_map_window`` (None: not yet) and solve the graph, so
        that the published poses follow; the matches join the graph as loops when their keyframes become nodes
        (they wait in the pending loops)."""
        if T_map_window is None:
            return
        n = self._localiser.last_agreeing
        self.graph.align_session(T_map_window @ inv_T(self.correction()))  # from where the graph has it now
        self._localiser, self.aligned_at_ns = None, int(stamp_ns)
        self.counts["map_relocalised"] += 1
        log.info("relocalised in the saved map at %d ns (%d agreeing matches): publishing in the map's frame",
                 stamp_ns, n)
        if self.graph.keys:
            t0 = time.perf_counter()
            self.graph.optimise(self.cfg.pose_graph_iterations)
            self.solve_ms.append(1e3 * (time.perf_counter() - t0))

    def sparse_map(self, session: dict | None = None, window: list[KeyframeRecord] = ()) -> SparseMap | None:
        """The map to save: the saved map's keyframes as loaded and, once aligned (always, without a saved map),
        this session's keyframes at their pose-graph estimates with their features and landmark positions moved
        the same way, then the keyframes of ``window`` (records of those still in the estimator's window, not yet
        nodes) moved by the newest node's correction; None when there is nothing to save."""
        g = self.graph
        meta = {"vocabulary": self.voc_id, "frame": "W",
                "cameras": [{"T_SC": T.tolist(), "focal_px": float(f)} for T, f in zip(self._T_SC, self._focal)],
                "sessions": [{**(session or {}), "keyframes": len(g.keys), "aligned": bool(self.aligned)}]}
        kfs, edges = [], []
        if self.aligned:
            for k in g.keys:
                T_corr = g.estimate[k] @ inv_T(g.odom[k])  # window frame -> map frame at this node
                fs, p_W = (self._old[k][0], self._old[k][1]) if k in self._old else (None, None)
                p = None if p_W is None else transform_points(T_corr, p_W)
                xy = None if fs is None else normalised_xy(fs, self._undistort)
                kfs.append((k, self.node_stamps[k], g.estimate[k], fs, p, xy))
            edges = [(a, b, T, c, ODOMETRY) for a, b, T, c in g.edges]
            edges += [(lp.old_key, lp.new_key, lp.T_old_new, lp.covariance, LOOP) for lp in g.loops
                      if not self._is_prior(lp.old_key)]
            self._add_window(kfs, edges, [r for r in window if r.state not in g.estimate])
        session_map = build_map(kfs, edges, meta)
        if self.prior is None:
            return session_map if len(session_map) else None
        links = [(int(self.prior.keys[lp.old_key - PRIOR_KEY_BASE]), lp.new_key, lp.T_old_new, lp.covariance, LOOP)
                 for lp in g.loops if self._is_prior(lp.old_key) and lp.new_key in g.odom] if self.aligned else []
        return concatenate(self.prior, session_map, np.eye(4), links)

    def _add_window(self, kfs: list, edges: list, window: list[KeyframeRecord]) -> None:
        """Append the window's keyframes (``sparse_map``) to ``kfs`` and ``edges``: each at its window pose moved by
        the newest node's correction, with its features where they are still held and enough of their landmarks
        are known (as a node's), linked to the keyframe before it by the window's relative pose (covariance
        ``WINDOW_EDGE_COV``: the window's marginals are not computed for a checkpoint)."""
        T_corr = self.graph.correction()
        prev = (kfs[-1][0], kfs[-1][2]) if kfs else None
        for rec in window:
            T = T_corr @ rec.T_WS
            fs, p, xy = self._features.get(rec.stamp_ns, (None, None))[0], None, None
            p_W = None if fs is None else self._landmarks_seen(fs, rec)
            if p_W is None:
                fs = None  # posed, but too few known landmarks to verify a match against
            else:
                p, xy = transform_points(T_corr, p_W), normalised_xy(fs, self._undistort)
            kfs.append((rec.state, rec.stamp_ns, T, fs, p, xy))
            if prev is not None:
                edges.append((prev[0], rec.state, inv_T(prev[1]) @ T, WINDOW_EDGE_COV, ODOMETRY))
            prev = (rec.state, T)
