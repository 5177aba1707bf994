"""Stretches of a trajectory's error: the first seconds and the fastest-turning window, against constructed runs."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from shared.metrics.ate import compute_ate
from services.app.metrics.segments import angular_speed, fastest_window, segment_errors


def _yaw_series(rate_of_t, seconds=60.0, hz=200):
    t = np.arange(0, seconds, 1 / hz)
    yaw = np.cumsum(rate_of_t(t)) / hz
    q = Rotation.from_euler("z", yaw[:, None]).as_quat()[:, [3, 0, 1, 2]]  # -> w x y z
    return (t * 1e9).astype(np.int64) + 10**18, q


def test_angular_speed_matches_the_constructed_rate():
    stamps, q = _yaw_series(lambda t: 0.5 + 0 * t)
    _, w = angular_speed(stamps, q)
    np.testing.assert_allclose(w, 0.5, atol=1e-6)


def test_fastest_window_finds_the_fast_stretch():
    rate = lambda t: np.where((t > 31) & (t < 39), 3.0, 0.2)  # noqa: E731
    stamps, q = _yaw_series(rate)
    t0, t1, speed = fastest_window(stamps, q, 10.0)
    s0, s1 = (t0 - stamps[0]) / 1e9, (t1 - stamps[0]) / 1e9
    assert s0 <= 31.01 and s1 >= 38.99 and abs((s1 - s0) - 10) < 0.01
    assert abs(speed - (8 * 3.0 + 2 * 0.2) / 10) < 0.01
    # restricted to a span that excludes it, it finds a slow window
    t0, _, speed = fastest_window(stamps, q, 10.0, within=(stamps[0], stamps[0] + 25 * 10**9))
    assert abs(speed - 0.2) < 1e-3


def test_segment_errors_split_the_run():
    stamps, q = _yaw_series(lambda t: np.where((t > 40) & (t < 50), 2.0, 0.1))
    p_gt = np.stack([np.cos(stamps * 1e-10), np.sin(stamps * 1e-10), np.zeros(len(stamps))], 1)
    err = np.zeros((len(stamps), 3))
    t = (stamps - stamps[0]) * 1e-9
    err[t < 10, 2] = 0.05     # a bad start
    err[(t > 40) & (t < 50), 2] = -0.02  # and a worse-than-usual fast stretch
    res = compute_ate(stamps, p_gt, stamps, p_gt + err, mode="none")
    seg = segment_errors(res, stamps, q, 10.0)
    assert abs(seg["first_rmse_m"] - 0.05) < 1e-3
    assert abs(seg["fastest_rmse_m"] - 0.02) < 2e-3 and 39.5 < seg["fastest_start_s"] < 40.5
    assert abs(seg["fastest_deg_s"] - np.degrees(2.0)) < 1.0
