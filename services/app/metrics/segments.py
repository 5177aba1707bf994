"""Where a trajectory's error is: the ATE of stretches of one SE(3)-aligned run (shared/metrics/ate.py).

The alignment is the whole run's; a stretch's figure is the RMSE of the per-pose errors inside it, so the stretches
add up to the run's RMSE and a bad start or a bad fast segment shows as a number beside it:

- ``first_s``: the first seconds after the first estimated pose (a start in motion, the initialisation);
- ``fastest``: the window of the given length where the ground truth turns fastest (mean angular speed, from
  the ground truth's orientations), the stretch a tracker loses first.
"""

from __future__ import annotations

import numpy as np

from shared.metrics.ate import AteResult


def window_rmse(res: AteResult, t0_ns: int, t1_ns: int) -> float:
    """RMSE [m] of the aligned per-pose errors with stamps in [t0_ns, t1_ns] (NaN when none is)."""
    keep = (res.stamps_ns >= t0_ns) & (res.stamps_ns <= t1_ns)
    return float(np.sqrt(np.mean(res.errors_m[keep] ** 2))) if keep.any() else float("nan")


def first_seconds_rmse(res: AteResult, seconds: float) -> float:
    """RMSE [m] over the first ``seconds`` of the estimate."""
    t0 = int(res.stamps_ns[0])
    return window_rmse(res, t0, t0 + int(seconds * 1e9))


def angular_speed(stamps_ns: np.ndarray, q_wxyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mid-point stamps [ns] and angular speeds [rad/s] between consecutive orientations (Hamilton w, x, y, z)."""
    q = np.asarray(q_wxyz, float)
    dot = np.abs(np.sum(q[1:] * q[:-1], axis=1)).clip(0.0, 1.0)
    dt = np.diff(np.asarray(stamps_ns, np.int64)) * 1e-9
    return (stamps_ns[1:] + stamps_ns[:-1]) // 2, 2.0 * np.arccos(dot) / dt


def fastest_window(stamps_ns: np.ndarray, q_wxyz: np.ndarray, seconds: float,
                   within: tuple[int, int] | None = None) -> tuple[int, int, float]:
    """``(t0_ns, t1_ns, mean angular speed [rad/s])`` of the ``seconds``-long window, inside ``within`` (stamps
    [ns]) when given, over which the ground truth turns fastest."""
    t, w = angular_speed(np.asarray(stamps_ns, np.int64), q_wxyz)
    if within is not None:
        keep = (t >= within[0]) & (t <= within[1])
        t, w = t[keep], w[keep]
    if len(t) < 2:
        raise ValueError("fastest_window: fewer than two orientations in the span")
    span = int(seconds * 1e9)
    if t[-1] - t[0] <= span:
        return int(t[0]), int(t[-1]), float(w.mean())
    # angle turned = integral of the speed; the window maximising it by cumulative sums over the samples
    dt = np.diff(t, prepend=t[0]) * 1e-9
    cum = np.concatenate([[0.0], np.cumsum(w * dt)])
    ends = np.searchsorted(t, t + span, side="right")  # first sample after each window
    valid = t + span <= t[-1]
    angle = np.where(valid, cum[ends] - cum[np.arange(len(t))], -1.0)
    i = int(np.argmax(angle))
    return int(t[i]), int(t[i] + span), float(angle[i] / seconds)


def segment_errors(res: AteResult, gt_stamps_ns: np.ndarray, gt_q_wxyz: np.ndarray, seconds: float = 10.0) -> dict:
    """The first-``seconds`` and fastest-``seconds`` figures of one aligned run, with the window found."""
    t0, t1, speed = fastest_window(gt_stamps_ns, gt_q_wxyz, seconds, within=(int(res.stamps_ns[0]),
                                                                            int(res.stamps_ns[-1])))
    return {"first_rmse_m": first_seconds_rmse(res, seconds), "fastest_rmse_m": window_rmse(res, t0, t1),
            "fastest_start_s": (t0 - int(res.stamps_ns[0])) * 1e-9, "fastest_deg_s": float(np.degrees(speed)),
            "seconds": seconds}
