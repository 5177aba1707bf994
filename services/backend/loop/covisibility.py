"""Covisibility: which keyframes observe which landmarks, and which keyframes share landmarks.

The mapping service asks :meth:`Covisibility.oldest_covisible` for the most overlapping submap (paper
sec. IV-C: the oldest covisible one with enough co-observed points)."""

from __future__ import annotations

from collections import Counter

import numpy as np


class Covisibility:
    def __init__(self) -> None:
        self._by_kf: dict[int, np.ndarray] = {}  # keyframe -> sorted unique landmark ids
        self._by_lm: dict[int, list[int]] = {}  # landmark -> keyframes in insertion order

    def add_keyframe(self, key: int, landmark_ids: np.ndarray) -> None:
        """Record (or replace) the landmarks a keyframe observes."""
        key = int(key)
        if key in self._by_kf:
            for lm in self._by_kf[key]:
                self._by_lm[int(lm)].remove(key)
        ids = np.unique(np.asarray(landmark_ids, np.int64))
        self._by_kf[key] = ids
        for lm in ids.tolist():
            self._by_lm.setdefault(lm, []).append(key)

    def __contains__(self, key: int) -> bool:
        return int(key) in self._by_kf

    def landmarks(self, key: int) -> np.ndarray:
        return self._by_kf.get(int(key), np.zeros(0, np.int64))

    def keyframes(self, landmark_id: int) -> list[int]:
        return list(self._by_lm.get(int(landmark_id), []))

    def shared(self, a: int, b: int) -> int:
        """Number of landmarks keyframes a and b both observe."""
        return len(np.intersect1d(self.landmarks(a), self.landmarks(b), assume_unique=True))

    def covisible(self, key: int, min_shared: int = 1) -> dict[int, int]:
        """Other keyframes sharing >= min_shared landmarks with ``key``: {keyframe: count}, most shared first."""
        c: Counter = Counter()
        for lm in self.landmarks(key).tolist():
            c.update(self._by_lm[lm])
        c.pop(int(key), None)
        return {k: n for k, n in c.most_common() if n >= min_shared}

    def covisible_with_landmarks(self, landmark_ids: np.ndarray, min_shared: int = 1) -> dict[int, int]:
        """Keyframes sharing >= min_shared of the given landmarks (e.g. a new frame's), most shared first."""
        c: Counter = Counter()
        for lm in np.unique(np.asarray(landmark_ids, np.int64)).tolist():
            c.update(self._by_lm.get(lm, []))
        return {k: n for k, n in c.most_common() if n >= min_shared}

    def oldest_covisible(self, key: int, min_shared: int) -> int | None:
        """The smallest (oldest) keyframe key sharing >= min_shared landmarks with ``key`` (None if none)."""
        cov = self.covisible(key, min_shared)
        return min(cov) if cov else None
