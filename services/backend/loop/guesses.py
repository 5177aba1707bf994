"""Guesses of one frame's pose in another (a session in a saved map, map B in map A), each from one verified match:
when two agree, and their mean."""

from __future__ import annotations

import numpy as np

from services.backend.loop.config import LoopConfig
from shared.geometry import so3_log


def agree(T1: np.ndarray, T2: np.ndarray, cfg: LoopConfig) -> bool:
    """Within ``loop.relocalise_agree_m`` and ``loop.relocalise_agree_deg`` of each other."""
    return (np.linalg.norm(T1[:3, 3] - T2[:3, 3]) <= cfg.relocalise_agree_m
            and np.rad2deg(np.linalg.norm(so3_log(T1[:3, :3].T @ T2[:3, :3]))) <= cfg.relocalise_agree_deg)


def mean_pose(Ts: list[np.ndarray]) -> np.ndarray:
    """The mean of nearby poses: mean translation, the rotation nearest the mean rotation matrix (chordal mean)."""
    U, _, Vt = np.linalg.svd(np.mean([T[:3, :3] for T in Ts], axis=0))
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, np.mean([T[:3, 3] for T in Ts], axis=0)
    return T
