"""Placing a session in a saved map's frame from its keyframes' verified matches to the map.

Each match gives one guess of ``T_map_window`` = (the keyframe's pose in the map, from PnP) x inverse(its pose in
the window's frame). The window pose comes from the keyframe's published state when that is known (the fast
path's pose, so the session can align while the keyframe is still in the window) or else from the pose-graph node
the keyframe becomes when it leaves the window. A pose estimated in the first ``loop.relocalise_settle_s`` of
tracking is not trusted (a window just initialised, e.g. a back end restarted in motion, has not settled): such a
match waits for its keyframe's node, whose pose the window has refined by then. A node that leaves the window still
within those first seconds (the window is short) gives an early guess. Once ``loop.relocalise_confirmations``
recent guesses, at least one of them settled, agree (``guesses.agree``), or ``loop.relocalise_early_confirmations``
early ones agree among themselves, their mean is the alignment. (Before early guesses counted, a back end restarted
beside its saved map dropped the matches of its first seconds there and, when the drone then left the mapped part,
relocalised only when it came back: 35 s later in the fault test, or never.)

:class:`MapLocaliser` keeps only this bookkeeping; the loop closer moves its pose graph when it returns a
transform (services/backend/loop/loop_closer.py).
"""

from __future__ import annotations

import collections

import numpy as np

from services.backend.loop.config import LoopConfig
from services.backend.loop.guesses import agree, mean_pose
from shared.geometry import inv_T

MAX_PUBLISHED = 64  # recent published window poses kept for matches that come after their state
MAX_WAITING = 200  # matches waiting for their keyframe's pose at most (oldest dropped)
RECENT_GUESSES = 10  # guesses the agreement test looks at


class MapLocaliser:
    """Guesses of T_map_window and when they agree. ``counts`` (shared with the loop closer) gets
    ``map_matches`` (guesses made) and ``map_matches_before_settled`` (those deferred or not trusted)."""

    def __init__(self, cfg: LoopConfig, counts: collections.Counter) -> None:
        self.cfg, self.counts = cfg, counts
        self._guesses: list[np.ndarray] = []  # recent T_map_window guesses from settled poses
        self._early: list[np.ndarray] = []  # recent guesses from nodes that left the window before it settled
        self._waiting: dict[int, object] = {}  # keyframe stamp -> its match (a VerifiedLoop), no trusted pose yet
        self._published: dict[int, np.ndarray] = {}  # keyframe stamp -> published window pose, no match yet
        self._tracking_since: int | None = None  # the first 'tracking' state's stamp
        self._latest_ns: int | None = None  # the newest state's stamp
        self.last_agreeing = 0  # guesses that agreed in the alignment returned last

    def _settled(self, pose_at_ns: int) -> bool:
        return (self._tracking_since is None
                or pose_at_ns >= self._tracking_since + self.cfg.relocalise_settle_s * 1e9)

    def _wait(self, stamp_ns: int, match) -> None:
        self._waiting[int(stamp_ns)] = match
        while len(self._waiting) > MAX_WAITING:
            self._waiting.pop(next(iter(self._waiting)))

    def _guess(self, T_map_window: np.ndarray, pose_at_ns: int) -> np.ndarray | None:
        """Add a guess whose window pose was estimated at ``pose_at_ns``; the alignment when enough agree."""
        self.counts["map_matches"] += 1
        if self._settled(pose_at_ns):
            self._guesses = (self._guesses + [T_map_window])[-RECENT_GUESSES:]
            pool, need = self._guesses + self._early, max(1, self.cfg.relocalise_confirmations)
        else:  # an early guess: supports settled ones; aligns alone only when enough early ones agree
            self.counts["map_matches_before_settled"] += 1
            self._early = (self._early + [T_map_window])[-RECENT_GUESSES:]
            pool, need = self._early, self.cfg.relocalise_early_confirmations or float("inf")
        agreeing = [T for T in pool if agree(T, T_map_window, self.cfg)]
        if len(agreeing) < need:
            return None
        self.last_agreeing = len(agreeing)
        return mean_pose(agreeing)

    def note_state(self, stamp_ns: int, status: str, T_W: np.ndarray | None) -> np.ndarray | None:
        """A published state: its status and its pose in the window's frame ``T_W`` (None when not wanted). Returns
        the alignment when the state completes it (a keyframe whose match came before its state)."""
        stamp_ns = int(stamp_ns)
        if status == "tracking" and self._tracking_since is None:
            self._tracking_since = stamp_ns
        self._latest_ns = max(stamp_ns, self._latest_ns or stamp_ns)
        if T_W is None:
            return None
        match = self._waiting.pop(stamp_ns, None)
        if match is None:
            self._published[stamp_ns] = np.asarray(T_W, float)
            while len(self._published) > MAX_PUBLISHED:
                self._published.pop(next(iter(self._published)))
            return None
        return self._from_state(stamp_ns, match, T_W)

    def _from_state(self, stamp_ns: int, match, T_W: np.ndarray) -> np.ndarray | None:
        if not self._settled(stamp_ns):  # not trusted: the keyframe's node will give the guess
            self.counts["map_matches"] += 1
            self.counts["map_matches_before_settled"] += 1
            self._wait(stamp_ns, match)
            return None
        return self._guess(match.T_WS_query @ inv_T(T_W), stamp_ns)

    def note_match(self, stamp_ns: int, match) -> np.ndarray | None:
        """A verified match of the keyframe at ``stamp_ns`` to the saved map; the alignment when it completes it."""
        T_W = self._published.pop(int(stamp_ns), None)
        if T_W is None:  # its state has not come yet
            self._wait(stamp_ns, match)
            return None
        return self._from_state(int(stamp_ns), match, T_W)

    def note_node(self, stamp_ns: int, T_W: np.ndarray) -> np.ndarray | None:
        """The keyframe at ``stamp_ns`` became a pose-graph node at window pose ``T_W``: a guess from it if its match
        is still waiting (estimated now, with everything the window has seen)."""
        match = self._waiting.pop(int(stamp_ns), None)
        if match is None:
            return None
        return self._guess(match.T_WS_query @ inv_T(T_W), self._latest_ns if self._latest_ns is not None else stamp_ns)
