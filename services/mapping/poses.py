"""Body poses by stamp for depth frames: a bounded buffer of estimator states, exact match within a
tolerance or interpolation (SLERP on rotation, linear on position) between the two neighbours."""

from __future__ import annotations

import bisect
import threading

import numpy as np

from shared.geometry import make_T, so3_exp, so3_log


class PoseBuffer:
    """Thread-safe ``stamp_ns -> T_WS`` buffer (the Zenoh callback adds, the main loop looks up)."""

    def __init__(self, capacity: int = 2000) -> None:
        self.capacity = int(capacity)
        self._stamps: list[int] = []
        self._poses: list[np.ndarray] = []
        self._lock = threading.Lock()

    def add(self, stamp_ns: int, T_WS: np.ndarray) -> None:
        T = np.array(T_WS, float)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise ValueError("T_WS must be a finite 4x4 matrix")
        with self._lock:
            i = bisect.bisect_left(self._stamps, stamp_ns)
            if i < len(self._stamps) and self._stamps[i] == stamp_ns:
                self._poses[i] = T  # a re-estimate of the same frame replaces the old one
                return
            self._stamps.insert(i, int(stamp_ns))
            self._poses.insert(i, T)
            if len(self._stamps) > self.capacity:
                del self._stamps[0], self._poses[0]

    def __len__(self) -> int:
        return len(self._stamps)

    @property
    def newest_ns(self) -> int | None:
        with self._lock:
            return self._stamps[-1] if self._stamps else None

    def lookup(self, stamp_ns: int, tolerance_ns: int, max_gap_ns: int) -> np.ndarray | None:
        """T_WS at ``stamp_ns``: the state within ``tolerance_ns``, else interpolated between neighbours
        at most ``max_gap_ns`` apart; None if neither (not yet arrived, or too old)."""
        with self._lock:
            i = bisect.bisect_left(self._stamps, stamp_ns)
            for j in (i - 1, i):
                if 0 <= j < len(self._stamps) and abs(self._stamps[j] - stamp_ns) <= tolerance_ns:
                    return self._poses[j].copy()
            if i == 0 or i == len(self._stamps):
                return None
            t0, t1 = self._stamps[i - 1], self._stamps[i]
            if t1 - t0 > max_gap_ns:
                return None
            A, B = self._poses[i - 1], self._poses[i]
        a = (stamp_ns - t0) / (t1 - t0)
        R = A[:3, :3] @ so3_exp(a * so3_log(A[:3, :3].T @ B[:3, :3]))
        return make_T(R, (1 - a) * A[:3, 3] + a * B[:3, 3])
