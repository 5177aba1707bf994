"""The window's observation bookkeeping: which landmark was seen by which camera at which state, which landmarks
are triangulated into the graph, and the reprojection factors built for them (cached, so a window rebuilt every
keyframe does not rebuild its factors).

``by_landmark`` is landmark -> state -> [(camera, normalised xy (2,)), ...]; the position j of an observation in its
list is part of its factor's cache key, so lists are only replaced whole (:meth:`ObservationBook.set`), which drops
their cached factors.
"""
from __future__ import annotations

from typing import Callable

import gtsam
import numpy as np


class ObservationBook:
    def __init__(self) -> None:
        self.by_landmark: dict[int, dict[int, list[tuple[int, np.ndarray]]]] = {}
        self.in_graph: set[int] = set()  # triangulated landmarks with factors in the window's graph
        self._factors: dict[tuple[int, int, int], gtsam.NonlinearFactor] = {}

    def add(self, state: int, lm: int, camera: int, xy: np.ndarray) -> None:
        self.by_landmark.setdefault(lm, {}).setdefault(state, []).append((camera, xy))

    def count(self, lm: int) -> int:
        """Observations of ``lm`` over the whole window (0 when unknown)."""
        return sum(len(o) for o in self.by_landmark.get(lm, {}).values())

    def seen_at(self, state: int) -> list[int]:
        """Landmarks in the graph observed at ``state``."""
        return [lm for lm in self.in_graph if state in self.by_landmark[lm]]

    def set(self, lm: int, state: int, keep: list) -> None:
        """The observations of ``lm`` at ``state`` replaced by ``keep`` (removed when empty); their cached factors
        go."""
        for j in range(len(self.by_landmark[lm][state])):
            self._factors.pop((lm, state, j), None)
        if keep:
            self.by_landmark[lm][state] = keep
        else:
            del self.by_landmark[lm][state]

    def forget_if_unobserved(self, lm: int) -> None:
        if not self.by_landmark.get(lm):
            self.by_landmark.pop(lm, None)

    def remove_state(self, state: int) -> list[int]:
        """Every observation at ``state`` removed; the landmarks left with fewer than two observations."""
        weak = []
        for lm in [lm for lm, by in self.by_landmark.items() if state in by]:
            self.set(lm, state, [])
            if self.count(lm) < 2:
                weak.append(lm)
        return weak

    def factor(self, lm: int, state: int, j: int, make: Callable[[], gtsam.NonlinearFactor]) -> gtsam.NonlinearFactor:
        """The reprojection factor of observation j of ``lm`` at ``state``, built by ``make`` the first time."""
        key = (lm, state, j)
        f = self._factors.get(key)
        if f is None:
            f = self._factors[key] = make()
        return f

    def of_state(self, state: int) -> dict[int, tuple[tuple[int, np.ndarray], ...]]:
        """landmark -> ((camera, xy), ...) at ``state``, in the order landmarks were first seen (a new dict)."""
        return {lm: tuple(by[state]) for lm, by in self.by_landmark.items() if state in by}
