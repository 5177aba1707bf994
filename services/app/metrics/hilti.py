"""Hilti SLAM Challenge 2022 score from sparse control points (paper sec. V, Table III).

Each control point is a known position p_W at a time. The estimate's pose nearest in time (within
``max_dt_ns``, 2 s by default) is associated with it; the associated estimate positions are aligned to the
control points in SE(3) (Umeyama without scale); each control point then earns points by its position error:

    error < 1 cm: 10,  1-3 cm: 6,  3-6 cm: 3,  6-10 cm: 1,  otherwise (or not associated): 0

(half-open intervals, the lower bound inclusive) and the sequence score is ``points / (N / 10)`` for N control
points, i.e. 0..100.

On our replicas, control points are sampled from the ground truth at camera frame times
(:func:`control_points_from_groundtruth`), so the nearest estimated pose is the one of the same frame.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from shared.metrics.ate import umeyama

# (upper bound of the error [m], points); errors at or above the last bound earn 0
THRESHOLDS = ((0.01, 10), (0.03, 6), (0.06, 3), (0.10, 1))
MAX_DT_NS = 2_000_000_000


def points_for_error(error_m: float) -> int:
    """Points of one control point with position error ``error_m`` [m] (NaN: not associated -> 0)."""
    if not np.isfinite(error_m):
        return 0
    for bound, pts in THRESHOLDS:
        if error_m < bound:
            return pts
    return 0


@dataclasses.dataclass(frozen=True)
class HiltiResult:
    score: float  # points / (N / 10), 0..100
    points: int
    n_control: int
    n_associated: int
    errors_m: np.ndarray  # (N,) per control point after alignment; NaN where not associated
    points_each: np.ndarray  # (N,) int

    def summary(self) -> dict:
        return {"score": self.score, "points": self.points, "n_control": self.n_control,
                "n_associated": self.n_associated, "errors_m": [None if not np.isfinite(e) else float(e)
                                                                for e in self.errors_m],
                "points_each": self.points_each.tolist()}


def nearest(stamps_ns: np.ndarray, query_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index of the nearest stamp in sorted ``stamps_ns`` for each query, and the absolute difference [ns]."""
    s = np.asarray(stamps_ns, np.int64)
    q = np.asarray(query_ns, np.int64)
    k = np.clip(np.searchsorted(s, q), 1, len(s) - 1) if len(s) > 1 else np.zeros(len(q), int)
    if len(s) > 1:
        left_closer = np.abs(q - s[k - 1]) <= np.abs(s[k] - q)
        k = np.where(left_closer, k - 1, k)
    return k, np.abs(s[k] - q)


def hilti_score(control_stamps_ns, control_p, est_stamps_ns, est_p, max_dt_ns: int = MAX_DT_NS) -> HiltiResult:
    """Score of an estimated trajectory (stamps sorted, positions (M,3) [m]) against control points (N,3) [m]."""
    cs = np.asarray(control_stamps_ns, np.int64)
    cp = np.asarray(control_p, float).reshape(-1, 3)
    es = np.asarray(est_stamps_ns, np.int64)
    ep = np.asarray(est_p, float).reshape(-1, 3)
    if len(cs) != len(cp) or len(cs) == 0:
        raise ValueError(f"need one stamp per control point and at least one point, got {len(cs)} and {len(cp)}")
    if len(es) != len(ep) or len(es) == 0:
        raise ValueError("the estimate is empty or its stamps and positions differ in length")
    if np.any(np.diff(es) < 0):
        raise ValueError("the estimate's stamps are not sorted")
    idx, dt = nearest(es, cs)
    assoc = dt <= max_dt_ns
    errors = np.full(len(cs), np.nan)
    if assoc.sum() >= 3:
        al = umeyama(ep[idx[assoc]], cp[assoc], with_scale=False)
        errors[assoc] = np.linalg.norm(al.apply(ep[idx[assoc]]) - cp[assoc], axis=1)
    elif assoc.any():  # too few for a rotation: translation only
        d = cp[assoc] - ep[idx[assoc]]
        errors[assoc] = np.linalg.norm(d - d.mean(axis=0), axis=1)
    pts = np.array([points_for_error(e) for e in errors], int)
    return HiltiResult(float(pts.sum() / (len(cs) / 10.0)), int(pts.sum()), len(cs), int(assoc.sum()), errors, pts)


def control_points_from_groundtruth(gt_stamps_ns, gt_p, frame_stamps_ns, n: int = 12,
                                    margin_s: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` control points at frame times spread evenly over the ground truth's span (``margin_s`` kept free at
    both ends), positions interpolated linearly in the ground truth."""
    gs = np.asarray(gt_stamps_ns, np.int64)
    gp = np.asarray(gt_p, float)
    fs = np.asarray(frame_stamps_ns, np.int64)
    m = int(margin_s * 1e9)
    fs = fs[(fs >= gs[0] + m) & (fs <= gs[-1] - m)]
    if len(fs) < n:
        raise ValueError(f"only {len(fs)} frame times inside the ground truth for {n} control points")
    pick = fs[np.round(np.linspace(0, len(fs) - 1, n)).astype(int)]
    t = (pick - gs[0]).astype(float)
    tg = (gs - gs[0]).astype(float)
    p = np.stack([np.interp(t, tg, gp[:, k]) for k in range(3)], axis=1)
    return pick, p
