"""Rules of the keyframe window that the estimator and the per-frame fast path share, kept apart from the
estimator's bookkeeping: which observations of a feature frame are usable, when a frame becomes a keyframe (also
what the fast path expects of the back end), which observations reproject too badly to stay, and the order in
which the window's variables are eliminated."""

from __future__ import annotations

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, L, V, X


class VioInputError(ValueError):
    """A frame whose arrays cannot be used (shape mismatch, time going backwards)."""


def observation_arrays(landmark_ids, camera_index, uv, n_cameras: int
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A feature frame's observations as (ids (M,) int64, cameras (M,) int64, uv (M, 2) float, usable (M,) bool):
    usable where the camera index is one of the rig's ``n_cameras`` and the pixel is finite. Raises
    :class:`VioInputError` when the arrays disagree in length."""
    ids = np.asarray(landmark_ids, np.int64).reshape(-1)
    cams = np.asarray(camera_index, np.int64).reshape(-1)
    uv = np.asarray(uv, float)
    if uv.shape != (len(ids), 2) or len(cams) != len(ids):
        raise VioInputError(f"observation arrays disagree: {len(ids)} ids, {len(cams)} camera indices, "
                                f"uv of shape {uv.shape}")
    return ids, cams, uv, (cams >= 0) & (cams < n_cameras) & np.all(np.isfinite(uv), axis=1)


def keyframe_due(stamp_ns: int, flagged: bool, last_keyframe_ns: int | None, max_interval_s: float) -> bool:
    """A frame becomes a keyframe when the frontend flagged it, when there is no keyframe yet (``None``: the
    window is not initialised), or when the last one is ``max_interval_s`` old."""
    return flagged or last_keyframe_ns is None or stamp_ns - last_keyframe_ns >= max_interval_s * 1e9


def reprojection_outliers(values: gtsam.Values, obs: dict, landmarks, states, T_SC: np.ndarray, focal: np.ndarray,
                          min_depth_m: float, max_error_px: float) -> dict[tuple[int, int], set[int]]:
    """(landmark, state) -> indices of that state's observations of the landmark that are behind the camera (closer
    than ``min_depth_m``) or reproject farther than ``max_error_px``, at the current ``values``. ``obs``:
    landmark -> state -> [(camera, normalised xy)]; ``landmarks``: those with a value; ``states``: the window's."""
    T_CW = {s: np.linalg.inv(values.atPose3(X(s)).matrix()[None] @ T_SC) for s in states}
    rows, Ts, ps, xys, cams = [], [], [], [], []
    for lm in landmarks:
        p = values.atPoint3(L(lm))
        for s, seen in obs[lm].items():
            for j, (cam, xy) in enumerate(seen):
                rows.append((lm, s, j))
                Ts.append(T_CW[s][cam])
                ps.append(p)
                xys.append(xy)
                cams.append(cam)
    if not rows:
        return {}
    Ts, ps = np.array(Ts), np.array(ps)
    p_C = np.einsum("nij,nj->ni", Ts[:, :3, :3], ps) + Ts[:, :3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.linalg.norm(p_C[:, :2] / p_C[:, 2:3] - np.array(xys), axis=1) * focal[np.array(cams)]
    bad = ~((p_C[:, 2] > min_depth_m) & (err <= max_error_px))
    out: dict[tuple[int, int], set[int]] = {}
    for k in np.flatnonzero(bad):
        lm, s, j = rows[k]
        out.setdefault((lm, s), set()).add(j)
    return out


def state_keys(n: int) -> list[int]:
    """gtsam keys of window state ``n``: pose X, velocity V, bias B (the order of its marginals and priors)."""
    return [X(n), V(n), B(n)]


def schur_ordering(landmarks, states, extrinsic_keys=()) -> gtsam.Ordering:
    """Elimination order of a window: the landmarks L (ids) first (their Schur complement: cheaper than COLAMD at
    the window's size), then each state's X, V, B (``states``: indices), then the extrinsic keys, which touch every
    observation."""
    order = gtsam.Ordering()
    for lm in landmarks:
        order.push_back(L(lm))
    for n in states:
        for key in state_keys(n):
            order.push_back(key)
    for key in extrinsic_keys:
        order.push_back(key)
    return order
