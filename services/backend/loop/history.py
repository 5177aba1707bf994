"""Keyframes that leave the estimator's window, kept for the pose graph, loop verification and final BA.

A :class:`KeyframeHistory` is one of the estimator's marginalisation listeners (``WindowedVioEstimator(...,
on_marginalise=[history])``, services/backend/window/protocols.py): :meth:`KeyframeHistory.on_marginalise` is called
just before the oldest keyframe is marginalised, while the window's marginals still hold it, and hands each new
record to the history's ``listeners`` (the loop closer), given at construction. It reads the window through the
estimator's read API. Each record keeps the keyframe's state, its observations (normalised coordinates per
camera), the positions of the landmarks it observed, the IMU factor to the next keyframe and the covariance of the
relative pose to the next keyframe from the window's joint marginal covariance.
:meth:`KeyframeHistory.capture_window` adds the keyframes still in the window at the end of a run.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, L, V, X

from services.backend.loop.pose_graph import relative_covariance


@dataclass
class KeyframeRecord:
    state: int  # the estimator's state index (gtsam keys X/V/B(state))
    stamp_ns: int
    T_WS: np.ndarray
    v_W: np.ndarray
    bias: gtsam.imuBias.ConstantBias
    obs: dict[int, list[tuple[int, np.ndarray]]]  # landmark -> [(camera, normalised xy)]
    landmarks: dict[int, np.ndarray]  # landmark -> p_W at capture
    next_state: int | None = None
    imu_to_next: gtsam.NonlinearFactor | None = None
    rel_cov_to_next: np.ndarray | None = None  # (6,6) covariance of T_S(this)S(next)
    T_WS_next: np.ndarray | None = None


class KeyframeHistory:
    """The records of the keyframes that left the window, oldest first; ``listeners`` get each new record."""

    def __init__(self, listeners: Sequence[Callable[[KeyframeRecord], None]] = ()) -> None:
        self.records: list[KeyframeRecord] = []
        self.listeners = tuple(listeners)
        self.fallback_covariances = 0  # relative covariances that could not be taken from the marginals

    def by_stamp(self) -> dict[int, KeyframeRecord]:
        return {r.stamp_ns: r for r in self.records}

    def _record(self, est, n: int) -> KeyframeRecord:
        vals = est.values
        obs = {lm: [(c, np.array(xy)) for c, xy in o] for lm, o in est.observations_of(n).items()}
        lms = {lm: np.asarray(vals.atPoint3(L(lm))) for lm in obs if est.landmark_in_graph(lm)}
        return KeyframeRecord(n, int(est.stamps[n]), vals.atPose3(X(n)).matrix(), np.asarray(vals.atVector(V(n))),
                              vals.atConstantBias(B(n)), obs, lms)

    def on_marginalise(self, est, old: int, new: int) -> None:
        """``old`` leaves the window of ``est``, ``new`` becomes its oldest keyframe (a MarginalisationListener)."""
        rec = self._record(est, old)
        rec.next_state = new
        rec.imu_to_next = est.imu_factor_to(new)
        rec.T_WS_next = est.values.atPose3(X(new)).matrix()
        cov = est.joint_marginal([X(old), X(new)])
        if cov is None or not np.all(np.isfinite(cov)):
            self.fallback_covariances += 1
            cov = np.diag([1e-4] * 3 + [1e-2] * 3 + [1e-4] * 3 + [1e-2] * 3)  # loose: 1 cm / 0.6 deg per keyframe
        rec.rel_cov_to_next = relative_covariance(rec.T_WS, rec.T_WS_next, cov)
        self.records.append(rec)
        for f in self.listeners:
            f(rec)

    def capture_window(self, est) -> list[KeyframeRecord]:
        """Records of the keyframes still in the window (end of a run), linked by the window's IMU factors."""
        kfs = list(est.keyframes)
        out = []
        for i, n in enumerate(kfs):
            rec = self._record(est, n)
            if i + 1 < len(kfs):
                rec.next_state = kfs[i + 1]
                rec.imu_to_next = est.imu_factor_to(kfs[i + 1])
            out.append(rec)
        return out
