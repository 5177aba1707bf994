"""The frame W' the back end publishes in (:class:`PublishedFrame`): the estimator's W moved by the loop closer's
correction, as the published states and keyframe poses carry it; the occupancy terms' submap anchoring."""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

import numpy as np
from gtsam.symbol_shorthand import X

from services.backend.loop.history import KeyframeHistory
from shared.geometry import inv_T
from shared.messages import Keyframes

if TYPE_CHECKING:
    from services.backend.window.estimator import WindowedVioEstimator


class PublishedFrame:
    """The frame W' the back end publishes in, as the loop closer moved it: the correction T_W'W applied to the
    last state and the keyframe poses the last ``Keyframes`` messages carried. The occupancy terms' submap
    anchoring (services/backend/window/protocols.py: SubmapAnchoring), since the mapping's submap poses and the depth poses
    live in that frame.

    ``window``: the estimator, read when a submap is anchored; a provider rather than the estimator itself, since
    this is made before the estimator (whose extra factors, the occupancy terms, need this)."""

    def __init__(self, history: KeyframeHistory, window: Callable[[], WindowedVioEstimator], correct_state: bool,
                 anchor_tolerance_ms: float) -> None:
        self.history, self.window = history, window
        self.correct_state, self.anchor_tolerance_ms = correct_state, anchor_tolerance_ms
        self.T_last = np.eye(4)  # the correction applied to the last state
        self.keyframe_poses: dict[int, np.ndarray] = {}  # keyframe state -> its pose in the last Keyframes message

    def anchor_of(self, stamp_ns: int, T_WM: np.ndarray) -> tuple[int, np.ndarray] | None:
        """The keyframe a submap created at ``stamp_ns`` with pose ``T_WM`` (as the mapping has it now) follows:
        the keyframe nearest its creation within ``o2p.anchor_tolerance_ms`` (state index) and ``T_KM``, taken
        against that keyframe's pose as it was last published (the frame the mapping's T_WM lives in): the pose of
        the last ``Keyframes`` message that carried it, not a newer correction the mapping has not seen yet."""
        tol = self.anchor_tolerance_ms * 1e6
        est = self.window()
        best: tuple[float, int, np.ndarray] | None = None
        for n in est.keyframes:  # still in the window
            if est.values.exists(X(n)) and abs(est.stamps[n] - stamp_ns) <= tol:
                if best is None or abs(est.stamps[n] - stamp_ns) < best[0]:
                    best = (abs(est.stamps[n] - stamp_ns), n, est.values.atPose3(X(n)).matrix())
        for r in reversed(self.history.records):  # marginalised, time order
            if r.stamp_ns < stamp_ns - tol:
                break
            if abs(r.stamp_ns - stamp_ns) <= tol and (best is None or abs(r.stamp_ns - stamp_ns) < best[0]):
                best = (abs(r.stamp_ns - stamp_ns), r.state, r.T_WS)
        if best is None:
            return None
        _, n, T_WK = best
        if self.correct_state:  # as published; never published (yet): moved by the last state's correction
            T_WK = self.keyframe_poses.get(n, self.T_last @ T_WK)
        return n, inv_T(T_WK) @ np.asarray(T_WM, float)

    def correction(self) -> np.ndarray | None:
        """T_W'W applied to the last published state (None without ``loop.correct_state``: W' = W)."""
        return self.T_last.copy() if self.correct_state else None

    def note_published(self, kfs: Keyframes) -> None:
        """Remember the keyframe poses a ``Keyframes`` message carries (:meth:`anchor_of` reads them)."""
        for n, T in zip(np.asarray(kfs.ids), np.asarray(kfs.T_WS)):
            self.keyframe_poses[int(n)] = T
