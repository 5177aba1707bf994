"""Which occupancy-to-point factors the back end's window gets (paper sec. IV-C), transport-free.

Inputs (fed by the back-end node, :meth:`OccupancyTerms.add_message`): finished submaps' near-surface fields (``map/field``), live stereo
depth frames (``depth/stereo``), the landmark ids of every feature frame, and optionally the fused-depth
points of finished submaps (map-to-map).

* **Frame-to-map**: a window state with a stereo depth frame at its stamp (or, within
  ``attach_tolerance_ms``, the nearest one, moved into its body frame by the relative pose of the two
  estimates) gets one factor with the
  ``max_points_frame`` lowest-sigma pixels (one candidate per image cell, so the points spread) against
  o(k). Depth arrives after the frame's own optimisation here (the networks are slower than the
  tracker), so the factor joins the window at the next window optimisation while the state is still in
  it, and stays until the state leaves.
* **o(k)**: the oldest finished submap (finished at least ``min_target_age_s`` before the frame; with the default 0
  a submap whose life reaches past the frame, e.g. the growing one holding the frame's own depth, is never o(k))
  covisible with the frame (>= ``min_covisible_landmarks`` landmark
  ids shared with the frames recorded during the submap's life) that has >= M_min of the points inside
  its observed field at the current estimate. A revisit brings new landmark ids, so a keyframe the loop closer
  matched to an earlier visit (:meth:`OccupancyTerms.note_loop`, the PnP inliers' old landmark ids) also counts
  as observing those: the submaps of the earlier visit become covisible.
* **Target pose**: a submap follows the keyframe nearest its creation (as in the mapping service); when
  that state is still in the window the factor acts on both poses, else the submap pose is held fixed at
  the newest T_WM received (the factor then acts like a geometric loop closure on the frame).
* **Map-to-map**: when submap m closes (its points arrive), m and o(m) are tied to the keyframes anchoring
  them (the keyframe nearest each submap's creation, as in the mapping service; the ``anchoring`` given at
  construction, the loop-closing back end's, gives its state and ``T_KM``) and a :class:`MapToMap` term is queued
  (:meth:`OccupancyTerms.pop_map_to_map`). The loop closer adds it to its pose graph between the two anchor
  keyframes once both have left the window, and to the final bundle adjustment (services/backend/loop/), so the
  submap poses are the variables, as in eq. 5. Without a loop closer there is no map-to-map term (counted).
* **Gates** (:func:`consistency`): before a factor enters a graph, at the current estimate, at least M_min and
  (frame-to-map only) ``min_inside_fraction`` of its points must lie inside the target's observed field, and its whitened squared
  error (rows capped by N_eff, as the graph would see it) must pass a chi-square test at ``gate_chi2_p`` with
  min(n_valid, N_eff) degrees of freedom: a frame or submap whose depth is grossly inconsistent with the map
  at the current estimate is rejected (counted ``gated_overlap`` / ``gated_chi2``, logged), not left to the
  Tukey loss, which only switches a factor off near the estimate where it was linearised.
* **Metric hold** (one camera): until the window has a metric scale (it stood still, or
  services/backend/window/mono_init.py rebuilt it) and ``mono_settle_s`` after, there are no dense factors, and depth
  frames and submaps begun before that are never used: their poses (and, for MVS, their depth) came from an
  estimate without scale (:meth:`OccupancyTerms.window_factors`: the terms are one of the estimator's extra-factor
  sources, services/backend/window/protocols.py).
"""

from __future__ import annotations

import collections
import dataclasses
import logging

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from services.backend.o2p.config import O2PConfig
from services.backend.window.mono_init import metric_hold
from services.backend.o2p.factor import OccupancyToPoint, trilinear_derivatives
from services.backend.o2p.gates import GateResult, consistency
from services.backend.o2p.map_to_map import MapToMap
from services.backend.window.protocols import SubmapAnchoring
from shared.messages import DepthFrame, OccupancyField
from shared.occupancy.message import field_of_message
from shared.occupancy.o2p_points import select_depth_points  # noqa: F401 (also used by callers)
from shared.occupancy.query import BlockField
from shared.geometry import inv_T, transform_points

log = logging.getLogger("sigmaslam.backend.o2p")


@dataclasses.dataclass
class _Submap:
    id: int
    field: BlockField
    l_min: float
    T_WM: np.ndarray
    start_ns: int
    end_ns: int
    landmarks: np.ndarray  # sorted unique ids seen during the submap's life
    points_M: np.ndarray | None = None  # map-to-map points in M and their sigmas
    sigma: np.ndarray | None = None
    anchor: tuple[int, np.ndarray] | None = None  # (keyframe state, T_KM) once the submap closed



class OccupancyTerms:
    """Keeps map and depth inputs; :meth:`factors` answers the factors of the current window.

    ``anchoring`` (the loop-closing back end's, services/backend/window/protocols.py): the keyframe each closed submap
    follows (map-to-map terms) and the correction T_W'W of the published frame W', where depth poses and submap
    poses T_WM arrive, relative to the window's frame W. None without a loop closer: no map-to-map terms (counted
    ``map_to_map_no_pose_graph``), W' = W."""

    def __init__(self, cfg: O2PConfig, anchoring: SubmapAnchoring | None = None) -> None:
        cfg.check()
        self.cfg = cfg
        self.anchoring = anchoring
        self.submaps: dict[int, _Submap] = {}
        self._frames: collections.deque[tuple[int, np.ndarray]] = collections.deque()  # (stamp, landmark ids)
        # stamp -> (p_S, sigma, T_WS estimate at the stamp or None)
        self._depth: collections.OrderedDict[int, tuple[np.ndarray, np.ndarray, np.ndarray | None]] = collections.OrderedDict()
        # (kind, state index, submap id) -> (factor data, gtsam factor) or None when no target was found
        self._built: dict[tuple[str, int, int], tuple[OccupancyToPoint, gtsam.NonlinearFactor] | None] = {}
        self.counts = collections.Counter()
        self._map_to_map: list[MapToMap] = []
        self._loop_landmarks: dict[int, np.ndarray] = {}  # keyframe stamp -> old landmark ids a verified loop matched
        # metric hold (window_factors): None = not known (factors() called directly: no restriction); else the
        # stamp from which depth and submaps may be used, and whether factors may be made yet
        self.hold_from_ns: int | None = None
        self._held = True
        self.gate_log: collections.deque[tuple[int, GateResult]] = collections.deque(maxlen=1000)  # (submap, result)

    # ------------------------------------------------------------------ inputs
    def note_frame(self, stamp_ns: int, landmark_ids: np.ndarray) -> None:
        """The landmark ids a frame observes (covisibility with submaps)."""
        self._frames.append((int(stamp_ns), np.unique(np.asarray(landmark_ids, np.int64))))
        horizon = int(stamp_ns) - int(self.cfg.landmark_history_s * 1e9)
        while self._frames and self._frames[0][0] < horizon:
            self._frames.popleft()

    def add_depth(self, stamp_ns: int, depth: np.ndarray, sigma: np.ndarray, K: np.ndarray, T_SC: np.ndarray,
                  T_WS: np.ndarray | None = None, stamps: dict[int, int] | None = None,
                  values: gtsam.Values | None = None) -> int:
        """Select a frame's points now (body frame S); returns how many points were kept.

        ``T_WS``: the estimate at its stamp. With the window's ``stamps``/``values`` too, a frame without a
        state of its own attaches now to the nearest window state within ``attach_tolerance_ms``, by the
        relative pose of estimates from the same solve (later solves move both together); without them it
        attaches when the factors are built."""
        if self._before_hold(int(stamp_ns)):  # placed (and, for MVS, computed) with poses without scale
            self.counts["depth_before_hold"] += 1
            return 0
        p_C, s = select_depth_points(depth, sigma, K, self.cfg.max_points_frame)
        if len(p_C) < self.cfg.min_points_in_field:
            self.counts["depth_too_few_points"] += 1
            return 0
        T_SC = np.asarray(T_SC, float)
        p_S = p_C @ T_SC[:3, :3].T + T_SC[:3, 3]
        key, T = int(stamp_ns), None if T_WS is None else self._to_window(np.asarray(T_WS, float))
        if T is not None and stamps is not None and values is not None:
            tol, attach = self.cfg.depth_stamp_tolerance_ms * 1e6, self.cfg.attach_tolerance_ms * 1e6
            near = {n: abs(t - key) for n, t in stamps.items() if abs(t - key) <= attach and values.exists(X(n))}
            if near:
                n = min(near, key=near.get)
                if near[n] > tol:
                    p_S = self._attached(p_S, values.atPose3(X(n)).matrix(), T)
                    if stamps[n] in self._depth:  # the state already has depth of its own or nearer
                        return 0
                key, T = stamps[n], None
        self._depth[key] = (p_S, s, T)
        while len(self._depth) > self.cfg.max_pending_depth:
            self._depth.popitem(last=False)
            self.counts["depth_dropped_old"] += 1
        return len(p_C)

    def add_field(self, msg) -> None:
        """A submap's field (shared.messages.OccupancyField): finished ones once, the growing one now and then;
        a repeat replaces the field, pose, life span and landmark set of that submap."""
        sid = int(msg.submap_id)
        old = self.submaps.get(sid)
        start = int(msg.header.stamp_ns)
        end = max(self._frames[-1][0] if self._frames else start, start)
        ids = [i for t, i in self._frames if start <= t <= end]
        lms = np.unique(np.concatenate(ids)) if ids else np.empty(0, np.int64)
        if old is not None and len(old.landmarks):  # frames before the history horizon stay counted
            lms = np.union1d(lms, old.landmarks)
        sm = _Submap(sid, field_of_message(msg), float(msg.l_min), np.asarray(msg.T_WM, float), start, end, lms)
        if old is not None:
            sm.points_M, sm.sigma, sm.anchor = old.points_M, old.sigma, old.anchor
        self.submaps[sid] = sm
        while len(self.submaps) > self.cfg.max_submaps:
            self.submaps.pop(min(self.submaps))

    def add_submap_points(self, submap_id: int, points_M: np.ndarray, sigma: np.ndarray) -> None:
        sm = self.submaps.get(int(submap_id))
        if sm is None:
            self.counts["points_without_field"] += 1
            return
        order = np.argsort(np.asarray(sigma, float), kind="stable")[: self.cfg.max_points_map]
        sm.points_M, sm.sigma = np.asarray(points_M, float)[order], np.asarray(sigma, float)[order]
        if self.cfg.map_to_map:
            self._queue_map_to_map(sm)

    def add_message(self, msg, est) -> None:
        """``map/field`` (OccupancyField), ``depth/stereo`` (DepthFrame) or ``map/o2p_points`` (SubmapPoints); a
        depth frame attaches to the window of ``est`` (the estimator). One that cannot be used is dropped
        (counted ``dropped_bad_input``, logged)."""
        try:
            if isinstance(msg, DepthFrame):
                T_WS = None if np.allclose(msg.T_WC, np.eye(4)) else msg.T_WC @ np.linalg.inv(msg.T_SC)
                self.add_depth(msg.header.stamp_ns, msg.surface_depth(), msg.sigma, msg.K, msg.T_SC, T_WS, est.stamps, est.values)
            elif isinstance(msg, OccupancyField):
                self.add_field(msg)
            else:
                self.add_submap_points(msg.submap_id, msg.points_M, msg.sigma)
        except ValueError as exc:
            self.counts["dropped_bad_input"] += 1
            log.warning("o2p input %s dropped: %s", type(msg).__name__, exc)

    def pop_map_to_map(self) -> list[MapToMap]:
        """Map-to-map terms queued since the last call (for the loop closer)."""
        out, self._map_to_map = self._map_to_map, []
        return out

    def _queue_map_to_map(self, m: _Submap) -> None:
        """m has closed (its points came after its last field): bind it to its anchor keyframe and queue its
        term against o(m), the oldest covisible closed submap with >= M_min of m's points in its field."""
        if self.anchoring is None:
            self.counts["map_to_map_no_pose_graph"] += 1
            return
        if self._before_hold(m.start_ns):
            self.counts["map_to_map_before_hold"] += 1
            return
        m.anchor = self.anchoring.anchor_of(m.start_ns, m.T_WM)
        if m.anchor is None:
            self.counts["map_to_map_no_anchor"] += 1
            return
        gap_ns = self.cfg.map_target_gap_s * 1e9
        cands = [o for o in self._covisible(m.landmarks, exclude=m.id)
                 if o.anchor is not None and o.id < m.id and not self._before_hold(o.start_ns)
                 and m.start_ns - o.end_ns >= gap_ns]
        o = self._o(cands, m.points_M, m.T_WM, exclude=m.id)
        if o is None:
            self.counts["map_to_map_no_target"] += 1
            return
        if o.anchor[0] == m.anchor[0]:  # both follow one keyframe: the term would be constant
            self.counts["map_to_map_same_anchor"] += 1
            return
        self._map_to_map.append(MapToMap(m.id, o.id, m.anchor[0], o.anchor[0], m.anchor[1], o.anchor[1], m.points_M,
                                         m.sigma, o.field, o.l_min, self.cfg))
        self.counts["map_to_map"] += 1

    # ------------------------------------------------------------------ factors
    def _attached(self, p_S: np.ndarray, T_WA: np.ndarray, T_WS: np.ndarray) -> np.ndarray:
        """Depth points of body frame S moved into the body frame of the window state A it attaches to, by the
        relative pose of the two estimates (both in the window's frame)."""
        self.counts["frame_to_map_attached"] += 1
        return transform_points(inv_T(T_WA) @ T_WS, p_S)

    def _correction(self) -> np.ndarray | None:
        """T_W'W, or None when the published frame is the window's."""
        return None if self.anchoring is None else self.anchoring.correction()

    def _to_window(self, T_pub: np.ndarray) -> np.ndarray:
        """A pose in the published frame W' (depth, submaps) expressed in the window's frame W."""
        C = self._correction()
        return T_pub if C is None else inv_T(C) @ T_pub

    def note_loop(self, stamp_ns: int, old_landmark_ids: np.ndarray) -> None:
        """A verified loop: the keyframe at ``stamp_ns`` sees these landmarks of an earlier visit (PnP inliers), so
        it is covisible with the submaps built then (landmark ids of a revisit are new, the tracker's are not)."""
        ids = np.unique(np.asarray(old_landmark_ids, np.int64))
        if len(ids):
            self._loop_landmarks[int(stamp_ns)] = ids
            self.counts["frames_with_loop_landmarks"] += 1
            while len(self._loop_landmarks) > self.cfg.max_pending_depth:
                self._loop_landmarks.pop(min(self._loop_landmarks))

    def _landmarks_near(self, stamp_ns: int) -> np.ndarray:
        ids = np.empty(0, np.int64)
        for t, got in reversed(self._frames):
            if t == stamp_ns:
                ids = got
                break
        loop = self._loop_landmarks.get(int(stamp_ns))
        return ids if loop is None else np.union1d(ids, loop)

    def _target_pose(self, sm: _Submap, stamps: dict[int, int], values: gtsam.Values) -> dict:
        """key_b/T_BM when the submap's anchor state is in the window, else the fixed T_WB = T_WM."""
        tol = int(self.cfg.depth_stamp_tolerance_ms * 1e6)
        for n, t in stamps.items():
            if abs(t - sm.start_ns) <= tol and values.exists(X(n)):
                return {"key_b": X(n), "T_BM": inv_T(values.atPose3(X(n)).matrix()) @ self._to_window(sm.T_WM)}
        return {"T_WB": self._to_window(sm.T_WM)}

    def _o(self, candidates: list[_Submap], p_A: np.ndarray, T_WA: np.ndarray, exclude: int = -1) -> _Submap | None:
        """Oldest candidate with >= M_min of the points inside its observed field."""
        for sm in sorted(candidates, key=lambda s: s.id):
            if sm.id == exclude:
                continue
            q = (p_A @ T_WA[:3, :3].T + T_WA[:3, 3] - sm.T_WM[:3, 3]) @ sm.T_WM[:3, :3]
            if int(trilinear_derivatives(sm.field, q)[3].sum()) >= self.cfg.min_points_in_field:
                return sm
        return None

    def _make(self, sm: _Submap, p_A, sig, key_a, stamps, values) -> tuple[OccupancyToPoint, gtsam.NonlinearFactor] | None:
        c = self.cfg
        tgt = self._target_pose(sm, stamps, values)
        if tgt.get("key_b") == key_a:
            return None
        f = OccupancyToPoint(sm.field, sm.l_min, p_A, sig, key_a=key_a, tukey_k=c.tukey_k, grad_min=c.grad_min,
                           info_scale=c.info_scale, effective_points=c.effective_points, **tgt)
        T_WB = values.atPose3(tgt["key_b"]).matrix() if "key_b" in tgt else tgt["T_WB"]
        g = consistency(f, values.atPose3(key_a).matrix(), T_WB, c)
        self.gate_log.append((sm.id, g))
        if g.reason:
            self.counts[f"gated_{g.reason}"] += 1
            log.info("o2p frame-to-map on submap %d rejected (%s): %d/%d points inside, chi2 %.1f (limit %.1f, dof %.0f)",
                     sm.id, g.reason, g.n_valid, g.n_points, g.chi2, g.limit, g.dof)
            return None
        log.debug("o2p frame-to-map on submap %d: %d/%d points inside, chi2 %.1f (limit %.1f, dof %.0f)",
                  sm.id, g.n_valid, g.n_points, g.chi2, g.limit, g.dof)
        return f, f.factor(g.n_valid)

    def _refixed(self, f: OccupancyToPoint, submap_id: int) -> tuple[OccupancyToPoint, gtsam.NonlinearFactor] | None:
        sm = self.submaps.get(submap_id)
        if sm is None:
            self.counts["factor_target_gone"] += 1
            return None
        g = OccupancyToPoint(f.field, f.l_min, f.p_A, f.sigma_d, key_a=f.key_a, T_WB=self._to_window(sm.T_WM), tukey_k=f.tukey_k,
                             grad_min=f.grad_min, info_scale=f.info_scale, effective_points=f.effective_points)
        self.counts["factor_target_fixed"] += 1
        return g, g.factor(f.n_valid_built)

    def _covisible(self, lms: np.ndarray, exclude: int = -1) -> list[_Submap]:
        need = self.cfg.min_covisible_landmarks
        return [sm for sm in self.submaps.values()
                if sm.id != exclude and np.isin(lms, sm.landmarks, assume_unique=True).sum() >= need]

    def window_factors(self, est) -> list[gtsam.NonlinearFactor]:
        """As the estimator's extra-factor source (services/backend/window/protocols.py): :meth:`factors` of its
        window once it has a metric hold (:func:`services.backend.window.mono_init.metric_hold`) and, with one camera,
        ``mono_settle_s`` after it got one; nothing before. Depth frames and submaps older than that moment
        are never used."""
        if not est.stamps:
            return []
        newest = max(est.stamps.values())
        if not metric_hold(est):
            if self._held:
                log.info("o2p: no dense factors while the window has no metric scale")
            self._held, self.hold_from_ns = False, None
            self.counts["window_without_metric_hold"] += 1
            return []
        if not self._held or self.hold_from_ns is None:
            settle = self.cfg.mono_settle_s if len(est.cameras) == 1 else 0.0
            self._held, self.hold_from_ns = True, newest + int(settle * 1e9)
            if settle > 0:
                log.info("o2p: window has a metric hold; dense factors from %.3f s on (depth and submaps before are not used)",
                         self.hold_from_ns * 1e-9)
        if newest < self.hold_from_ns:
            self.counts["window_settling"] += 1
            return []
        return self.factors(est.stamps, est.values)

    def _before_hold(self, stamp_ns: int) -> bool:
        return not self._held or (self.hold_from_ns is not None and stamp_ns < self.hold_from_ns)

    def factors(self, stamps: dict[int, int], values: gtsam.Values) -> list[gtsam.NonlinearFactor]:
        """Factors for the window whose states are ``stamps`` (state index -> stamp) at estimate ``values``;
        a factor is built once and kept while its state is in the window."""
        c = self.cfg
        live = {n for n in stamps if values.exists(X(n))}
        self._built = {k: v for k, v in self._built.items() if k[1] in live}
        for k, v in list(self._built.items()):  # a target state left the window: hold that submap where it is now
            if v is not None and v[0].key_b is not None and not values.exists(v[0].key_b):
                self._built[k] = self._refixed(v[0], k[2])
        if c.frame_to_map and self.submaps:
            tol = int(c.depth_stamp_tolerance_ms * 1e6)
            attach = int(c.attach_tolerance_ms * 1e6)
            done = {k[1] for k in self._built if k[0] == "f2m"}
            for t in [t for t in self._depth if self._before_hold(t)]:
                del self._depth[t]
                self.counts["depth_before_hold"] += 1
            for n in sorted(live - done):
                gap = {t: abs(t - stamps[n]) for t, d in self._depth.items()
                       if abs(t - stamps[n]) <= tol or (d[2] is not None and abs(t - stamps[n]) <= attach)}
                if not gap:
                    continue
                t = min(gap, key=gap.get)
                p_S, sig, T_WS = self._depth.pop(t)
                T_WA = values.atPose3(X(n)).matrix()
                if gap[t] > tol:
                    p_S = self._attached(p_S, T_WA, T_WS)
                C = self._correction()
                T_pub = T_WA if C is None else C @ T_WA  # o(k) in the submaps' frame
                cands = [sm for sm in self._covisible(self._landmarks_near(stamps[n])) if not self._before_hold(sm.start_ns)]
                old = [sm for sm in cands if stamps[n] - sm.end_ns >= c.min_target_age_s * 1e9]
                self.counts["frame_to_map_recent_targets_skipped"] += len(cands) - len(old)
                sm = self._o(old, p_S, T_pub)
                built = None if sm is None else self._make(sm, p_S, sig, X(n), stamps, values)
                self._built[("f2m", n, -1 if sm is None else sm.id)] = built
                self.counts["frame_to_map" if built else "frame_to_map_no_target"] += 1
        return [v[1] for v in self._built.values() if v is not None]
