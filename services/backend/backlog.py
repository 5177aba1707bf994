"""Catching up when the back end falls behind its input (BRIEF sec. 7: degrade, count, never fall behind).

Feature frames that wait in the back end's queue make every later pose late by the time they take. When more
than ``max_backlog`` frames wait, the oldest frames that are not keyframes are skipped: their IMU samples are
still integrated (they are kept separately), tracks continue through the next processed frame, and keyframes
(which the loop closure and the map refer to by id) are always processed.
"""
from __future__ import annotations

from typing import Sequence, TypeVar

F = TypeVar("F")


def shed_backlog(frames: Sequence[F], max_backlog: int, is_keyframe=lambda f: bool(f.is_keyframe)) -> tuple[list[F], int]:
    """Frames to process (oldest first) and how many were skipped; keeps every keyframe and the newest
    ``max_backlog`` frames. ``max_backlog <= 0`` keeps everything."""
    frames = list(frames)
    if max_backlog <= 0 or len(frames) <= max_backlog:
        return frames, 0
    cut = len(frames) - max_backlog
    kept = [f for i, f in enumerate(frames) if i >= cut or is_keyframe(f)]
    return kept, len(frames) - len(kept)
