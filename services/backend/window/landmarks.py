"""The window's landmarks the back end publishes (``estimator/landmarks``: the MVS prior, the viewer)."""
from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L


@dataclass(frozen=True)
class WindowLandmarks:
    """Well-constrained landmarks of the window: triangulated, finite, >= 2 observations (N rows each)."""

    ids: np.ndarray  # (N,) int64
    p_W: np.ndarray  # (N,3) [m]
    num_observations: np.ndarray  # (N,) int32, observations in the window
    last_seen_ns: np.ndarray  # (N,) int64, stamp of the newest window state that observes the landmark


def select_landmarks(ids, p_W, num_observations, last_seen_ns, limit: int) -> WindowLandmarks:
    """The finite ones, at most ``limit``: those last seen most recently, then seen most often; in id order."""
    ids, nobs = np.array(ids, np.int64), np.array(num_observations, np.int32)
    last, p = np.array(last_seen_ns, np.int64), np.array(p_W, np.float64).reshape(-1, 3)
    ok = np.isfinite(p).all(axis=1)
    ids, p, nobs, last = ids[ok], p[ok], nobs[ok], last[ok]
    order = np.lexsort((ids, -nobs, -last))[:max(0, int(limit))]  # newest first, then most observed
    order = order[np.argsort(ids[order])]
    return WindowLandmarks(ids[order], p[order], nobs[order], last[order])


def gather_landmarks(obs: dict, in_graph: set[int], values: gtsam.Values, stamps: dict[int, int],
                     limit: int) -> WindowLandmarks:
    """:func:`select_landmarks` of the window's triangulated landmarks with >= 2 observations, at the estimate
    ``values``: ``obs`` landmark -> state -> [(camera, xy)], ``stamps`` state -> stamp [ns]."""
    ids, p, nobs, last = [], [], [], []
    for lm in in_graph:
        by_state = obs.get(lm, {})
        n_obs = sum(len(o) for o in by_state.values())
        if n_obs < 2 or not values.exists(L(lm)):
            continue
        ids.append(lm)
        p.append(values.atPoint3(L(lm)))
        nobs.append(n_obs)
        last.append(max(stamps[s] for s in by_state))
    return select_landmarks(ids, p, nobs, last, limit)
