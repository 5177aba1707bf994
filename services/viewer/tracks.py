"""Trajectories and landmarks as the viewer keeps them (bounded, with change tracking). No viser, no Zenoh.

The causal trajectory is held in fixed-size chunks: a full chunk never changes again, so the drawer
sends it once and afterwards re-sends only the growing tail chunk.
"""

from __future__ import annotations

import numpy as np

from shared.euroc import PoseSeries
from shared.metrics.ate import align_posyaw, associate, umeyama

CHUNK = 256


class ChunkedTrajectory:
    """Positions p_W with stamps; chunk k holds points k*CHUNK .. (k+1)*CHUNK (its last point is the first of
    chunk k+1, so the drawn line is continuous). At most about ``max_points`` are kept: beyond, the oldest
    chunk is dropped."""

    def __init__(self, max_points: int = 20000) -> None:
        self.max_chunks = max(2, int(np.ceil(max_points / CHUNK)))
        cap = (self.max_chunks + 1) * CHUNK
        self._p = np.empty((cap, 3))
        self._t = np.empty(cap, np.int64)
        self._base = 0  # global index of the oldest kept point (a multiple of CHUNK)
        self._n = 0  # global index of the next point
        self._dirty: set[int] = set()
        self._removed: set[int] = set()
        self.dropped_out_of_order = 0

    def append(self, stamp_ns: int, p_W: np.ndarray) -> bool:
        """Add one position; a stamp not after the previous one is dropped (counted) and returns False."""
        if self._n > self._base and stamp_ns <= self._t[self._n - 1 - self._base]:
            self.dropped_out_of_order += 1
            return False
        if self._n - self._base == len(self._p):  # full: drop the oldest chunk
            self._p[:-CHUNK] = self._p[CHUNK:].copy()
            self._t[:-CHUNK] = self._t[CHUNK:].copy()
            self._removed.add(self._base // CHUNK)
            self._dirty.discard(self._base // CHUNK)
            self._base += CHUNK
        i = self._n - self._base
        self._p[i] = p_W
        self._t[i] = stamp_ns
        k = self._n // CHUNK
        self._dirty.add(k)
        if self._n % CHUNK == 0 and k - 1 >= self._base // CHUNK:
            self._dirty.add(k - 1)  # the previous chunk gains its joint point
        self._n += 1
        return True

    def chunk_points(self, k: int) -> np.ndarray:
        lo = max(k * CHUNK, self._base)
        hi = min((k + 1) * CHUNK + 1, self._n)
        return self._p[lo - self._base:hi - self._base]

    def take_changes(self) -> tuple[dict[int, np.ndarray], tuple[int, ...]]:
        """(changed chunk index -> its points (copy), removed chunk indices) since the last call."""
        changed = {k: self.chunk_points(k).copy() for k in sorted(self._dirty)}
        removed = tuple(sorted(self._removed))
        self._dirty.clear()
        self._removed.clear()
        return changed, removed

    def all_points(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps (N,), positions (N,3)) of every kept point, oldest first."""
        m = self._n - self._base
        return self._t[:m].copy(), self._p[:m].copy()

    def __len__(self) -> int:
        return self._n - self._base

    @property
    def latest(self) -> np.ndarray | None:
        return self._p[self._n - 1 - self._base].copy() if self._n > self._base else None


class KeyframeTrack:
    """Latest optimised position per keyframe id (Keyframes messages update a subset)."""

    def __init__(self) -> None:
        self.ids = np.zeros(0, np.int64)
        self.stamps_ns = np.zeros(0, np.int64)
        self.p_W = np.zeros((0, 3))
        self.changed = False

    def update(self, ids: np.ndarray, stamps_ns: np.ndarray, T_WS: np.ndarray) -> None:
        ids = np.asarray(ids, np.int64)
        p = np.asarray(T_WS, np.float64)[:, :3, 3]
        all_ids = np.concatenate([self.ids, ids])
        all_t = np.concatenate([self.stamps_ns, np.asarray(stamps_ns, np.int64)])
        all_p = np.concatenate([self.p_W, p])
        # keep the last occurrence of every id (new values win), ordered by time
        _, rev_idx = np.unique(all_ids[::-1], return_index=True)
        keep = len(all_ids) - 1 - rev_idx
        keep = keep[np.argsort(all_t[keep], kind="stable")]
        self.ids, self.stamps_ns, self.p_W = all_ids[keep], all_t[keep], all_p[keep]
        self.changed = True

    def take(self) -> np.ndarray | None:
        if not self.changed:
            return None
        self.changed = False
        return self.p_W.copy()


class LandmarkBuffer:
    """Sparse landmark positions from estimator/landmarks: a bounded ring of (id, p_W); the newest per id wins
    (landmarks that left the estimator's window stay at their last estimate)."""

    def __init__(self, capacity: int = 20000) -> None:
        self.capacity = max(1, int(capacity))
        self._ids = np.full(self.capacity, -1, np.int64)
        self._p = np.zeros((self.capacity, 3))
        self._next = 0
        self._count = 0
        self.changed = False

    def add(self, ids: np.ndarray, p_W: np.ndarray) -> int:
        ids = np.asarray(ids, np.int64)
        p = np.asarray(p_W, np.float64)
        ok = np.isfinite(p).all(axis=1)
        ids, p = ids[ok][-self.capacity:], p[ok][-self.capacity:]
        n = len(ids)
        if n == 0:
            return 0
        slots = (self._next + np.arange(n)) % self.capacity
        self._ids[slots] = ids
        self._p[slots] = p
        self._next = int((self._next + n) % self.capacity)
        self._count = min(self.capacity, self._count + n)
        self.changed = True
        return n

    def positions(self) -> np.ndarray:
        """(L,3) one position per landmark id (its newest)."""
        if self._count == 0:
            return np.zeros((0, 3))
        order = (self._next - self._count + np.arange(self._count)) % self.capacity  # oldest -> newest
        ids = self._ids[order]
        _, rev_idx = np.unique(ids[::-1], return_index=True)
        return self._p[order[len(ids) - 1 - rev_idx]]

    def take(self) -> np.ndarray | None:
        if not self.changed:
            return None
        self.changed = False
        return self.positions()


class GroundTruthOverlay:
    """A ground-truth trajectory aligned to the causal estimate ('se3', 'posyaw' or 'none')."""

    MIN_MATCHES = 10

    def __init__(self, gt: PoseSeries, align: str = "se3", max_draw_points: int = 5000) -> None:
        self.gt = gt
        self.align = align
        step = max(1, int(np.ceil(len(gt) / max_draw_points)))
        self._draw = gt.p_WS[::step]
        self.aligned_with = -1  # number of matches of the last alignment (-1: never)
        self.changed = True
        self.points_W = self._draw.copy() if align == "none" else None

    def realign(self, est_stamps_ns: np.ndarray, est_p_W: np.ndarray) -> bool:
        """Re-align when the estimate has grown by half since the last alignment; True if the overlay moved."""
        if self.align == "none":
            return False
        ia, ib = associate(est_stamps_ns, self.gt.stamps_ns, max_diff_ns=20_000_000)
        n = len(ia)
        if n < self.MIN_MATCHES or (self.aligned_with > 0 and n < 1.5 * self.aligned_with):
            return False
        # alignment maps GT into the estimate's W: dst = estimate, src = ground truth
        src, dst = self.gt.p_WS[ib], np.asarray(est_p_W)[ia]
        a = umeyama(src, dst, with_scale=False) if self.align == "se3" else align_posyaw(src, dst)
        self.points_W = a.apply(self._draw)
        self.aligned_with = n
        self.changed = True
        return True

    def take(self) -> np.ndarray | None:
        if not self.changed or self.points_W is None:
            return None
        self.changed = False
        return self.points_W.copy()
