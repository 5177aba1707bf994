"""Catching up when a stage falls behind its input (BRIEF sec. 7: degrade, count, never fall behind): the back end,
the fast path driven on its own and the frontend process (camera frames) shed through it.

Feature frames that wait in a queue make every later output late by the time they take. When more than
``max_backlog`` frames wait, the oldest frames that are not keyframes are skipped: their IMU samples are still
integrated (they are kept separately) and tracks continue through the next processed frame. Keyframes are kept,
unless more than ``max_keyframes`` of them wait (the back end's window optimisation slower than the keyframe
rate for a while, on a starved machine): then the oldest are skipped too, so that the window, and the fast path
anchored on it, stays current; the loop closer forgets the descriptors of keyframes the estimator never made.
"""
from __future__ import annotations

from typing import Sequence, TypeVar

F = TypeVar("F")


def shed_backlog(frames: Sequence[F], max_backlog: int, is_keyframe=lambda f: bool(f.is_keyframe),
                 max_keyframes: int = 0) -> tuple[list[F], int]:
    """Frames to process (oldest first) and how many were skipped; keeps the newest ``max_backlog`` frames and the
    keyframes (the newest ``max_keyframes`` of them when > 0). ``max_backlog <= 0`` keeps everything."""
    frames = list(frames)
    if max_backlog <= 0 or len(frames) <= max_backlog:
        return frames, 0
    cut = len(frames) - max_backlog
    kf_index = [i for i, f in enumerate(frames) if i < cut and is_keyframe(f)]
    if max_keyframes > 0:
        n_recent_kf = sum(1 for f in frames[cut:] if is_keyframe(f))
        kf_index = kf_index[max(0, len(kf_index) - max(0, max_keyframes - n_recent_kf)):]
    keep = set(kf_index) | set(range(cut, len(frames)))
    kept = [f for i, f in enumerate(frames) if i in keep]
    return kept, len(frames) - len(kept)
