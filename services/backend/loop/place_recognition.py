"""Keyframe database of bags of words: which earlier keyframe shows the place the current one sees?

A query scores the current bag against every stored keyframe older than ``min_age_s`` (recent ones look
alike because they are neighbours, not revisits). As in DBoW2, the raw L1 score is normalised by the score
of the current keyframe with its predecessor (how similar "the same place" looks right now), so one
threshold works for textured and plain scenes; candidates must also pass an absolute floor.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.backend.loop.vocabulary import l1_score


@dataclass(frozen=True)
class PlaceCandidate:
    key: int  # the stored keyframe's key
    stamp_ns: int
    score: float  # raw L1 score
    normalised: float  # score / score with the predecessor


class PlaceDatabase:
    """Bags of stored keyframes (dense rows, grown in blocks) and their keys and stamps."""

    def __init__(self, vocabulary_size: int) -> None:
        self.size = vocabulary_size
        self._bags = np.zeros((64, vocabulary_size), np.float32)
        self.keys: list[int] = []
        self.stamps_ns: list[int] = []

    def __len__(self) -> int:
        return len(self.keys)

    def add(self, key: int, stamp_ns: int, bag: np.ndarray) -> None:
        if bag.shape != (self.size,):
            raise ValueError(f"bag of shape {bag.shape}, expected ({self.size},)")
        n = len(self.keys)
        if n == len(self._bags):
            self._bags = np.concatenate([self._bags, np.zeros_like(self._bags)])
        self._bags[n] = bag
        self.keys.append(int(key))
        self.stamps_ns.append(int(stamp_ns))

    def scores(self, bag: np.ndarray) -> np.ndarray:
        """Raw L1 scores (len,) of ``bag`` against every stored keyframe."""
        return l1_score(bag, self._bags[:len(self.keys)]) if self.keys else np.zeros(0)

    def query(self, bag: np.ndarray, stamp_ns: int, min_age_s: float, min_score: float, min_normalised: float,
              reference_score: float | None = None, max_candidates: int = 3) -> list[PlaceCandidate]:
        """Best stored keyframes at least ``min_age_s`` older than ``stamp_ns``, best first.

        ``reference_score``: the score of this bag with its predecessor keyframe (default: with the newest
        stored keyframe)."""
        if not self.keys or not bag.any():
            return []
        s = self.scores(bag)
        ref = float(s[-1]) if reference_score is None else float(reference_score)
        old = np.asarray(self.stamps_ns) <= stamp_ns - int(min_age_s * 1e9)
        ok = np.flatnonzero(old & (s >= min_score) & (s >= min_normalised * max(ref, 1e-9)))
        ok = ok[np.argsort(-s[ok])][:max_candidates]
        return [PlaceCandidate(self.keys[i], self.stamps_ns[i], float(s[i]), float(s[i] / max(ref, 1e-9)))
                for i in ok]
