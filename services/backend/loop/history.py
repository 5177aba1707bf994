"""Keyframes that leave the estimator's window, kept for the pose graph, loop verification and final BA.

:func:`attach` installs :meth:`KeyframeHistory.capture` as the estimator's ``on_marginalise`` hook (called
just before the oldest keyframe is marginalised, while the window's marginals still hold it). Each record
keeps the keyframe's state, its observations (normalised coordinates per camera), the positions of the
landmarks it observed, the IMU factor to the next keyframe and the covariance of the relative pose to the
next keyframe from the window's joint marginal covariance. :meth:`KeyframeHistory.capture_window` adds the
keyframes still in the window at the end of a run.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

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


@dataclass
class KeyframeHistory:
    records: list[KeyframeRecord] = field(default_factory=list)
    listeners: list[Callable[[KeyframeRecord], None]] = field(default_factory=list)
    fallback_covariances: int = 0  # relative covariances that could not be taken from the marginals

    def by_stamp(self) -> dict[int, KeyframeRecord]:
        return {r.stamp_ns: r for r in self.records}

    def _record(self, est, n: int) -> KeyframeRecord:
        vals = est.values
        obs = {lm: [(c, np.array(xy)) for c, xy in by[n]] for lm, by in est._obs.items() if n in by}
        lms = {lm: np.asarray(vals.atPoint3(L(lm))) for lm in obs if lm in est._in_graph}
        return KeyframeRecord(n, int(est.stamps[n]), vals.atPose3(X(n)).matrix(), np.asarray(vals.atVector(V(n))),
                              vals.atConstantBias(B(n)), obs, lms)

    def capture(self, est, old: int, new: int) -> None:
        """Hook: ``old`` leaves the window, ``new`` becomes the oldest keyframe."""
        rec = self._record(est, old)
        rec.next_state = new
        rec.imu_to_next = est._imu_factors.get(new)
        rec.T_WS_next = est.values.atPose3(X(new)).matrix()
        cov = None
        if est._marginals is not None:
            try:
                cov = est._marginals.jointMarginalCovariance([X(old), X(new)]).fullMatrix()
            except RuntimeError:
                cov = None
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
                rec.imu_to_next = est._imu_factors.get(kfs[i + 1])
            out.append(rec)
        return out


def attach(estimator) -> KeyframeHistory:
    """A history fed by ``estimator``'s marginalisation hook."""
    h = KeyframeHistory()
    estimator.on_marginalise = h.capture
    return h
