"""Non-causal output: one bundle adjustment over every keyframe of a run, with IMU and loop factors.

The graph holds every keyframe's (pose, velocity, bias) linked by the IMU factors the window used, every
recorded observation as a Cauchy-robust reprojection factor (the window's noise model), landmarks seen at
least twice (initial positions: their last window estimate), the accepted loop constraints (relative poses,
and the loop keyframe's PnP inliers as observations of the old landmarks), and a gauge prior on the first
keyframe, and the map-to-map occupancy-to-point terms (eq. 5-7) between keyframes anchoring submaps. A loop's PnP
inlier says that the query feature's own landmark (a new track of the point) is the old landmark it matched: the
two are merged into one, so every keyframe that saw the new track observes the old landmark (not merged when a
keyframe observes both: they are not one point then). With ``prune_ratio`` the graph is solved twice, the second
time without the landmarks that fit badly after the first (a track sliding along a silhouette or drifting is not
a point, and the whole-run solve bends the poses to fit it). Frames between keyframes keep their causal motion under
a correction blended from the two keyframes around them (:func:`follow_keyframes`).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, L, V, X

from services.backend.loop.history import KeyframeRecord
from shared.vio.vision_factors import ProjectionModel
from shared.geometry import inv_T, so3_exp, so3_log


@dataclass(frozen=True)
class FinalBaResult:
    stamps_ns: np.ndarray  # (K,) keyframe stamps
    T_WS: np.ndarray  # (K,4,4) optimised keyframe poses
    landmarks: int
    observations: int
    initial_error: float
    final_error: float  # of the graph solved last (without the pruned landmarks)
    map_to_map: int = 0  # map-to-map terms in the graph
    merged: int = 0  # landmarks merged into an older one through loop observations
    pruned: int = 0  # landmarks dropped before the second solve (their reprojection error too large)


def bundle_adjust(records: list[KeyframeRecord], cameras, sigma_px: float = 1.0, cauchy_k: float = 2.0,
                  loops: list[tuple[int, int, np.ndarray, np.ndarray]] = (), max_iterations: int = 30,
                  prior_sigma_rot: float = 1e-3, prior_sigma_pos: float = 1e-3,
                  loop_observations: list[tuple[int, int, np.ndarray, int, int]] = (), map_to_map=(), anchors=(),
                  T_init: np.ndarray | None = None, merge_loop_landmarks: bool = True,
                  prune_ratio: float = 0.0) -> FinalBaResult:
    """``records`` of all keyframes (time order, no duplicates); ``cameras``: the estimator's VioCamera
    list; ``loops``: (old state, new state, T_old_new, covariance 6x6); ``loop_observations``: (state, camera,
    normalised xy, old landmark id, the feature's own landmark id) observations of old landmarks by loop keyframes
    (PnP inliers); ``merge_loop_landmarks``: merge each such own landmark into the old one; ``map_to_map``:
    services.backend.o2p.terms.MapToMap terms (those whose anchors are among the keyframes join); ``anchors``:
    (state, T_WS, covariance 6x6) poses of keyframes in a saved map's frame (their matches to the map's fixed
    keyframes): robust pose priors that place the whole run in the map's frame, the first keyframe's gauge prior
    then only weak; ``T_init``: moves the records' poses, velocities and landmarks (window frame) to where the
    optimisation starts (the map's frame as the pose graph has it); ``prune_ratio`` > 0: a second solve, from the
    first one's result, without the landmarks whose RMS reprojection error there exceeds ``prune_ratio`` times the
    median landmark's (tracks that slid along a silhouette or drifted: they pull the poses; 0 = one solve)."""
    recs = sorted({r.state: r for r in records}.values(), key=lambda r: r.state)
    if len(recs) < 2:
        raise ValueError("the final bundle adjustment needs at least two keyframes")
    states = {r.state for r in recs}
    anchors = [a for a in anchors if a[0] in states]
    T0 = np.eye(4) if T_init is None else np.asarray(T_init, float)
    if anchors:  # the saved map's matches place the run; the first keyframe only weakly
        prior_sigma_rot, prior_sigma_pos = 1.0, 100.0
    g, vals = _keyframes(recs, states, anchors, T0, prior_sigma_rot, prior_sigma_pos)
    obs, p_init = _observations(recs)
    root = _merge_landmarks(obs, p_init, [(lm, own) for _, _, _, lm, own in loop_observations]) \
        if merge_loop_landmarks else {}
    n_lm, n_obs, lm_factors = _landmarks(g, vals, obs, p_init, states, ProjectionModel(cameras, sigma_px, cauchy_k),
                                         cameras, loop_observations, root, T0)
    n_m2m = _loops_and_map(g, recs, states, loops, map_to_map, T0)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(1e-5)
    e0 = g.error(vals)
    out = gtsam.LevenbergMarquardtOptimizer(g, vals, params).optimize()
    bad = _badly_fitting(g, out, lm_factors, prune_ratio) if prune_ratio > 0 else set()
    if bad:
        drop = {i for lm in bad for i, _ in lm_factors[lm]}
        g2 = gtsam.NonlinearFactorGraph()
        for i in range(g.size()):
            if i not in drop:
                g2.add(g.at(i))
        for lm in bad:
            out.erase(L(lm))
        g = g2
        out = gtsam.LevenbergMarquardtOptimizer(g, out, params).optimize()
        n_lm -= len(bad)
        n_obs -= len(drop)
    return FinalBaResult(np.array([r.stamp_ns for r in recs], np.int64),
                         np.array([out.atPose3(X(r.state)).matrix() for r in recs]), n_lm, n_obs, e0, g.error(out),
                         n_m2m, len(root), len(bad))


def _keyframes(recs: list[KeyframeRecord], states: set[int], anchors, T0: np.ndarray, prior_sigma_rot: float,
               prior_sigma_pos: float) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """Every keyframe's (pose, velocity, bias) moved by ``T0``, the IMU factors between them, the anchors' robust
    pose priors and the gauge priors on the first keyframe."""
    g, vals = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for r in recs:
        vals.insert(X(r.state), gtsam.Pose3(T0 @ r.T_WS))
        vals.insert(V(r.state), T0[:3, :3] @ np.asarray(r.v_W, float))
        vals.insert(B(r.state), r.bias)
        if r.imu_to_next is not None and r.next_state in states:
            g.add(r.imu_to_next)
    r0 = recs[0]
    for s, T, cov in anchors:
        g.add(gtsam.PriorFactorPose3(X(s), gtsam.Pose3(np.asarray(T, float)), gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Cauchy.Create(3.0), gtsam.noiseModel.Gaussian.Covariance(np.asarray(cov, float)))))
    g.add(gtsam.PriorFactorPose3(X(r0.state), gtsam.Pose3(T0 @ r0.T_WS), gtsam.noiseModel.Diagonal.Sigmas(
        np.array([prior_sigma_rot] * 3 + [prior_sigma_pos] * 3))))
    g.add(gtsam.PriorFactorVector(V(r0.state), T0[:3, :3] @ np.asarray(r0.v_W, float),
                                  gtsam.noiseModel.Isotropic.Sigma(3, 0.1)))
    g.add(gtsam.PriorFactorConstantBias(B(r0.state), r0.bias, gtsam.noiseModel.Diagonal.Sigmas(
        np.array([0.1] * 3 + [0.01] * 3))))
    return g, vals


def _observations(recs: list[KeyframeRecord]) -> tuple[dict, dict]:
    """(landmark -> [(state, camera, xy)] across the keyframes, landmark -> its newest position estimate)."""
    obs: dict[int, list[tuple[int, int, np.ndarray]]] = {}
    p_init: dict[int, np.ndarray] = {}
    for r in recs:
        for lm, lst in r.obs.items():
            obs.setdefault(lm, []).extend((r.state, c, xy) for c, xy in lst)
        p_init.update(r.landmarks)
    return obs, p_init


def _landmarks(g, vals, obs: dict, p_init: dict, states, projection: ProjectionModel, cameras, loop_observations,
               root: dict, T0: np.ndarray) -> tuple[int, int, dict[int, list[tuple[int, float]]]]:
    """The landmarks of ``obs`` seen from two keyframes or more (with the loop keyframes' PnP inliers, through the
    merged landmarks of ``root``) and their reprojection factors (the window's); (landmarks, observations, landmark
    -> [(factor index, focal length [px])])."""
    for s, c, xy, lm, _ in loop_observations:
        lm = root.get(lm, lm)
        if s in states and lm in obs and all(s != s2 for s2, _, _ in obs[lm]):
            obs[lm].append((s, c, np.asarray(xy, float)))
    n_lm = n_obs = 0
    lm_factors: dict[int, list[tuple[int, float]]] = {}
    for lm, lst in obs.items():
        if lm not in p_init or len({s for s, _, _ in lst}) < 2:
            continue
        vals.insert(L(lm), T0[:3, :3] @ np.asarray(p_init[lm], float) + T0[:3, 3])
        n_lm += 1
        for s, c, xy in lst:
            lm_factors.setdefault(lm, []).append((g.size(), cameras[c].focal_px))
            g.add(projection.factor(np.asarray(xy, float), c, X(s), L(lm)))
            n_obs += 1
    return n_lm, n_obs, lm_factors


def _loops_and_map(g, recs, states, loops, map_to_map, T0: np.ndarray) -> int:
    """The loop constraints (Cauchy-robust relative poses) and the map-to-map terms between keyframes; returns how
    many map-to-map terms joined."""
    for old, new, T_rel, cov in loops:
        if old in states and new in states:
            model = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(3.0),
                                                   gtsam.noiseModel.Gaussian.Covariance(np.asarray(cov, float)))
            g.add(gtsam.BetweenFactorPose3(X(old), X(new), gtsam.Pose3(T_rel), model))
    n_m2m = 0
    T_of = {r.state: T0 @ r.T_WS for r in recs}
    for t in map_to_map:
        if t.state_m in states and t.state_o in states:
            f = t.build(X(t.state_m), X(t.state_o), T_of[t.state_m], T_of[t.state_o])
            if f is not None:
                g.add(f)
                n_m2m += 1
    return n_m2m


def _badly_fitting(g: gtsam.NonlinearFactorGraph, values: gtsam.Values, lm_factors: dict[int, list[tuple[int, float]]],
                   ratio: float) -> set[int]:
    """Landmarks whose RMS reprojection error [px] at ``values`` exceeds ``ratio`` times the median landmark's."""
    if not lm_factors:
        return set()
    rms = {lm: np.sqrt(np.mean([float(np.sum(np.square(g.at(i).unwhitenedError(values)))) * f ** 2 for i, f in fs]))
           for lm, fs in lm_factors.items()}
    limit = ratio * float(np.median(list(rms.values())))
    return {lm for lm, r in rms.items() if r > limit}


def _merge_landmarks(obs: dict[int, list], p_init: dict[int, np.ndarray], pairs: list[tuple[int, int]]) -> dict[int, int]:
    """Merge landmark ``own`` into ``old`` for each pair, in ``obs`` (landmark -> [(state, camera, xy)]) and
    ``p_init`` (landmark -> initial position) in place: the merged landmark keeps the old id and the old initial
    position (the new one's where the old has none). Returns merged id -> the id it joined.
    Pairs whose landmarks are observed by one keyframe in common are left apart."""
    root: dict[int, int] = {}
    find = lambda i: find(root[i]) if i in root else i  # noqa: E731
    for old, own in pairs:
        a, b = find(int(old)), find(int(own))
        if a == b or a not in obs or b not in obs:
            continue
        if {s for s, _, _ in obs[a]} & {s for s, _, _ in obs[b]}:
            continue
        obs[a].extend(obs.pop(b))
        if a not in p_init and b in p_init:
            p_init[a] = p_init[b]
        root[b] = a
    return {i: find(i) for i in root}


def follow_keyframes(stamps_ns: np.ndarray, T_causal: np.ndarray, kf_stamps_ns: np.ndarray,
                     kf_T_final: np.ndarray, kf_T_anchor: np.ndarray | None = None) -> np.ndarray:
    """Non-causal poses (N,4,4) of all frames from their causal poses ``T_causal`` and the keyframes' final poses.
    A keyframe's frame gets its final pose. A frame between two keyframes keeps its causal motion, corrected by
    ``C = T_final T_causal^-1`` taken from the keyframe before it (against its anchor) and from the one after it
    (against that keyframe's own causal pose, which the frames before it are consistent with), blended linearly
    in time (rotation on the geodesic): the correction leaves no step at a keyframe. Frames before the first keyframe
    move with it, frames after the last with its anchor. ``kf_T_anchor`` (K,4,4): the causal pose of each keyframe
    that the frames after it were solved against (default, or NaN: its frame's causal pose; the window's solve where
    the published state at a keyframe is the fast path's prediction). A keyframe is used when its stamp is among the
    frame stamps or its anchor is given."""
    stamps_ns = np.asarray(stamps_ns, np.int64)
    T_causal = np.asarray(T_causal, float)
    idx = {int(s): i for i, s in enumerate(stamps_ns)}
    kf_stamps_ns, kf_T_final = np.asarray(kf_stamps_ns, np.int64), np.asarray(kf_T_final, float)
    anchor = (np.full((len(kf_stamps_ns), 4, 4), np.nan) if kf_T_anchor is None
              else np.asarray(kf_T_anchor, float).reshape(-1, 4, 4))
    known = np.isfinite(anchor).all(axis=(1, 2))
    framed = np.array([int(s) in idx for s in kf_stamps_ns], bool)
    have = framed | known
    if not have.any():
        raise ValueError("no keyframe stamp is among the frame stamps, and no keyframe has an anchor")
    kf_stamps_ns, kf_T_final, anchor, known, framed = (a[have] for a in (kf_stamps_ns, kf_T_final, anchor, known, framed))
    # a keyframe's causal pose: its frame's; a keyframe without a published frame (the back end's first, while the
    # published state said 'initialising') has its anchor for both
    T_kf = np.array([T_causal[idx[int(s)]] if f else A for s, f, A in zip(kf_stamps_ns, framed, anchor)])
    anchor = np.where(known[:, None, None], anchor, T_kf)
    c_after = kf_T_final @ inv_T(anchor)
    c_before = kf_T_final @ inv_T(T_kf)
    j = np.searchsorted(kf_stamps_ns, stamps_ns, side="right") - 1  # the keyframe at or before each frame
    corr = np.where((j < 0)[:, None, None], c_before[0], c_after[np.clip(j, 0, None)])
    mid = np.flatnonzero((j >= 0) & (j < len(kf_stamps_ns) - 1))
    if len(mid):
        jm = j[mid]
        a = (stamps_ns[mid] - kf_stamps_ns[jm]) / (kf_stamps_ns[jm + 1] - kf_stamps_ns[jm])
        D = inv_T(c_after[jm]) @ c_before[jm + 1]
        step = np.tile(np.eye(4), (len(mid), 1, 1))
        step[:, :3, :3] = so3_exp(a[:, None] * so3_log(D[:, :3, :3]))
        step[:, :3, 3] = a[:, None] * D[:, :3, 3]
        corr[mid] = c_after[jm] @ step
    out = corr @ T_causal
    out[[idx[int(s)] for s in kf_stamps_ns[framed]]] = kf_T_final[framed]
    return out
