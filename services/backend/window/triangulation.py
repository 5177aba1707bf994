"""Landmark triangulation from normalised observations in posed cameras (linear DLT + checks)."""

from __future__ import annotations

import numpy as np


def triangulate(T_CW: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Point in W from K >= 2 views: ``T_CW`` (K,4,4) world-to-camera, ``xy`` (K,2) normalised coordinates."""
    A = np.concatenate([xy[:, 0:1] * T_CW[:, 2, :] - T_CW[:, 0, :], xy[:, 1:2] * T_CW[:, 2, :] - T_CW[:, 1, :]])
    _, _, vt = np.linalg.svd(A)
    h = vt[-1]
    if abs(h[3]) < 1e-12:
        return np.full(3, np.nan)
    return h[:3] / h[3]


def reprojection(T_CW: np.ndarray, xy: np.ndarray, p_W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(depth (K,), error (K,) in normalised units) of ``p_W`` in each view."""
    p_C = np.einsum("kij,j->ki", T_CW[:, :3, :3], p_W) + T_CW[:, :3, 3]
    z = p_C[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.linalg.norm(p_C[:, :2] / z[:, None] - xy, axis=1)
    return z, np.where(z > 0, err, np.inf)


def max_parallax_rad(T_CW: np.ndarray, xy: np.ndarray) -> float:
    """Largest angle between the observation rays, in W."""
    rays_C = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    rays_W = np.einsum("kji,kj->ki", T_CW[:, :3, :3], rays_C)  # R_WC = R_CW^T
    rays_W /= np.linalg.norm(rays_W, axis=1, keepdims=True)
    cos = np.clip(rays_W @ rays_W.T, -1.0, 1.0)
    return float(np.arccos(cos.min()))


def triangulate_checked(T_CW: np.ndarray, xy: np.ndarray, focal_px: np.ndarray, min_parallax_rad: float,
                        max_err_px: float, min_depth: float, max_depth: float) -> np.ndarray | None:
    """Triangulated point, or None when parallax, cheirality, depth range or reprojection error fail."""
    if len(xy) < 2 or max_parallax_rad(T_CW, xy) < min_parallax_rad:
        return None
    p = triangulate(T_CW, xy)
    if not np.all(np.isfinite(p)):
        return None
    z, err = reprojection(T_CW, xy, p)
    if np.any(z < min_depth) or np.all(z > max_depth) or np.any(err * focal_px > max_err_px):
        return None
    return p


def new_landmarks(obs: dict, in_graph: set, state: int, T_WS_of, T_SC: np.ndarray, focal_px: np.ndarray, cfg
                  ) -> list[tuple[int, np.ndarray]]:
    """(landmark, p_W) of the window's landmarks seen at ``state`` and not yet in the graph that triangulate from
    all their observations (``obs``: landmark -> state -> [(camera, normalised xy)]; ``T_WS_of(state)`` the body
    pose (4,4); ``cfg``: the back end's checks), at most as many as keep the graph within ``cfg.max_landmarks``."""
    out: list[tuple[int, np.ndarray]] = []
    for lm, by_state in obs.items():
        if lm in in_graph or state not in by_state or len(in_graph) + len(out) >= cfg.max_landmarks:
            continue
        if sum(len(o) for o in by_state.values()) < 2:
            continue
        T_CW, xy, f = [], [], []
        for s, views in by_state.items():
            T_WS = T_WS_of(s)
            for c, p in views:
                T_CW.append(np.linalg.inv(T_WS @ T_SC[c]))
                xy.append(p)
                f.append(focal_px[c])
        p = triangulate_checked(np.array(T_CW), np.array(xy), np.array(f), np.deg2rad(cfg.min_parallax_deg),
                                cfg.max_reproj_error_px, cfg.min_depth_m, cfg.max_depth_m)
        if p is not None:
            out.append((lm, p))
    return out
