"""Relative body rotation between two times from gyro samples (the frontend's motion prior)."""

from __future__ import annotations

import numpy as np

from shared.geometry import so3_exp


class GyroIntegrator:
    """Time-ordered gyro samples; :meth:`rotation` integrates R_S(t0)S(t1) over any covered interval.

    Between samples the mean of the two readings is held (trapezoid); the interval ends are linearly
    interpolated. Out-of-order or non-finite samples are dropped and counted."""

    def __init__(self, max_samples: int = 4000) -> None:
        self.stamps_ns = np.zeros(0, np.int64)
        self.omega = np.zeros((0, 3))
        self.max_samples = max_samples
        self.dropped = 0
        self._pending_t: list[int] = []
        self._pending_w: list[np.ndarray] = []

    def add(self, stamp_ns: int, omega_S: np.ndarray) -> None:
        w = np.asarray(omega_S, float).reshape(3)
        last = self._pending_t[-1] if self._pending_t else (self.stamps_ns[-1] if len(self.stamps_ns) else None)
        if not np.all(np.isfinite(w)) or (last is not None and stamp_ns <= last):
            self.dropped += 1
            return
        self._pending_t.append(int(stamp_ns))
        self._pending_w.append(w)

    def _flush(self) -> None:
        if self._pending_t:
            self.stamps_ns = np.concatenate([self.stamps_ns, np.array(self._pending_t, np.int64)])[-self.max_samples:]
            self.omega = np.concatenate([self.omega, np.array(self._pending_w)])[-self.max_samples:]
            self._pending_t, self._pending_w = [], []

    def covers(self, t0_ns: int, t1_ns: int) -> bool:
        self._flush()
        return len(self.stamps_ns) >= 2 and self.stamps_ns[0] <= t0_ns and self.stamps_ns[-1] >= t1_ns

    def rotation(self, t0_ns: int, t1_ns: int, gyro_bias: np.ndarray | None = None) -> np.ndarray | None:
        """R_S(t0)S(t1) (maps vectors of the body at t1 into the body at t0); None when not covered."""
        if not self.covers(t0_ns, t1_ns) or t1_ns < t0_ns:
            return None
        t, w = self.stamps_ns, self.omega
        if gyro_bias is not None:
            w = w - np.asarray(gyro_bias, float)
        i0 = max(int(np.searchsorted(t, t0_ns, side="right")) - 1, 0)
        i1 = min(int(np.searchsorted(t, t1_ns, side="left")), len(t) - 1)
        knots = np.concatenate([[t0_ns], t[i0 + 1:i1], [t1_ns]]).astype(np.int64)
        wk = np.stack([np.interp(knots, t, w[:, k]) for k in range(3)], axis=1)
        R = np.eye(3)
        steps = so3_exp(0.5 * (wk[:-1] + wk[1:]) * (np.diff(knots) * 1e-9)[:, None])  # ~10 per camera frame
        for R_step in steps:
            R = R @ R_step
        return R

    def prune_before(self, stamp_ns: int) -> None:
        """Forget samples older than the one just before ``stamp_ns``."""
        self._flush()
        i = max(int(np.searchsorted(self.stamps_ns, stamp_ns, side="right")) - 1, 0)
        self.stamps_ns, self.omega = self.stamps_ns[i:], self.omega[i:]
