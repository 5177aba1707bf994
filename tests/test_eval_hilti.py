"""Hilti 2022 scoring (services/app/metrics/hilti.py, sigmaslam eval hilti) against hand-computed cases."""

from __future__ import annotations

import numpy as np
import pytest

from shared.geometry import so3_exp
from services.app.metrics.hilti import control_points_from_groundtruth, hilti_score, nearest, points_for_error


def test_points_per_error_band():
    # half-open bands [lower, upper): <1 cm 10, 1-3 cm 6, 3-6 cm 3, 6-10 cm 1, else 0
    cases = {0.0: 10, 0.0099: 10, 0.01: 6, 0.0299: 6, 0.03: 3, 0.0599: 3, 0.06: 1, 0.0999: 1, 0.10: 0, 1.0: 0,
             float("nan"): 0}
    for err, pts in cases.items():
        assert points_for_error(err) == pts, err


def _track(n=10):
    stamps = np.arange(n, dtype=np.int64) * 5_000_000_000  # a control point every 5 s
    p = np.stack([np.linspace(0, 9, n), np.sin(np.arange(n)), 0.3 * np.cos(np.arange(n) * 0.7)], axis=1)
    return stamps, p


def test_perfect_estimate_in_another_frame_scores_100():
    cs, cp = _track()
    R = so3_exp(np.array([0.1, -0.2, 0.9]))
    est = cp @ R.T + np.array([3.0, -1.0, 0.5])  # same shape, rigidly moved: SE(3) alignment undoes it
    res = hilti_score(cs, cp, cs + 1_000_000, est)  # 1 ms later: nearest-time association
    assert res.score == pytest.approx(100.0)
    assert res.points == 100 and res.n_associated == 10
    assert np.nanmax(res.errors_m) < 1e-9


def test_unassociated_control_points_score_zero():
    cs, cp = _track()
    keep = np.ones(10, bool)
    keep[[3, 7]] = False  # no estimated pose within 2 s of these control points
    res = hilti_score(cs, cp, cs[keep], cp[keep])
    assert res.n_associated == 8
    assert res.points == 80
    assert res.score == pytest.approx(80 / (10 / 10))
    assert np.isnan(res.errors_m[[3, 7]]).all()


def test_association_window_is_two_seconds():
    cs, cp = _track(4)
    res = hilti_score(cs, cp, cs + 2_000_000_000, cp)  # exactly 2 s: still associated
    assert res.n_associated == 4
    res = hilti_score(cs, cp, cs + 2_000_000_001, cp)
    assert res.n_associated == 0 and res.score == 0.0


def test_one_bad_point_among_twenty():
    # 20 exact points and one 5 cm off. Hand computation: the alignment moves the outlier by ~1/20 of its offset
    # toward the control point and the others by as little, so the outlier keeps ~4.6 cm (3 points), the rest
    # stay under 1 cm (10 points each): score = (19 * 10 + 3) / (20 / 10) = 96.5.
    cs, cp = _track(20)
    est = cp.copy()
    est[5] += np.array([0.0, 0.0, 0.05])
    res = hilti_score(cs, cp, cs, est)
    assert 0.03 < res.errors_m[5] < 0.05
    assert np.delete(res.errors_m, 5).max() < 0.01
    assert res.score == pytest.approx(96.5)


def test_nearest_picks_the_closer_stamp():
    idx, dt = nearest(np.array([0, 10, 20]), np.array([-5, 4, 6, 15, 16, 30]))
    assert idx.tolist() == [0, 0, 1, 1, 2, 2]
    assert dt.tolist() == [5, 4, 4, 5, 4, 10]


def test_bad_input_is_a_clear_error():
    cs, cp = _track(3)
    with pytest.raises(ValueError):
        hilti_score(cs, cp[:2], cs, cp)
    with pytest.raises(ValueError):
        hilti_score(cs, cp, cs[::-1], cp)
    with pytest.raises(ValueError):
        hilti_score(cs, cp, cs[:0], cp[:0])


def test_control_points_from_groundtruth_interpolate_at_frame_times():
    gs = np.arange(0, 20_000_000_001, 5_000_000, dtype=np.int64)  # 200 Hz for 20 s
    gp = np.stack([gs / 1e9, 2 * gs / 1e9, np.zeros(len(gs))], axis=1)
    frames = np.arange(0, 20_000_000_001, 50_000_000, dtype=np.int64) + 2_500_000  # 20 Hz, between GT samples
    cs, cp = control_points_from_groundtruth(gs, gp, frames, n=6, margin_s=1.0)
    assert len(cs) == 6 and np.isin(cs, frames).all()
    assert cs[0] >= 1_000_000_000 and cs[-1] <= 19_000_000_000
    np.testing.assert_allclose(cp[:, 0], cs / 1e9, atol=1e-9)
    np.testing.assert_allclose(cp[:, 1], 2 * cs / 1e9, atol=1e-9)
    with pytest.raises(ValueError):
        control_points_from_groundtruth(gs, gp, frames[:3], n=6)


def test_eval_hilti_command(tmp_path, capsys):
    import argparse

    from services.app.eval.hilti_cmd import add_arguments, main

    cs, cp = _track()
    ctrl = tmp_path / "control.csv"
    ctrl.write_text("# stamp_ns,x,y,z\n" + "".join(f"{s},{x},{y},{z}\n" for s, (x, y, z) in zip(cs, cp)))
    est = tmp_path / "est.txt"  # TUM: t[s] x y z qx qy qz qw
    est.write_text("".join(f"{s / 1e9:.9f} {x} {y} {z + 0.02} 0 0 0 1\n" for s, (x, y, z) in zip(cs, cp)))
    p = argparse.ArgumentParser()
    add_arguments(p)
    assert main(p.parse_args(["--est", str(est), "--control", str(ctrl)])) == 0
    assert "Hilti score 100.00" in capsys.readouterr().out  # a constant offset is removed by the alignment
    bad = tmp_path / "bad.csv"
    bad.write_text("1,2\n")
    assert main(p.parse_args(["--est", str(est), "--control", str(bad)])) == 1
    assert "stamp_ns,x,y,z" in capsys.readouterr().out
