"""Estimator diagnostics (tools/eval/diagnose.py): errors against a constructed run with known errors."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from tools.eval.diagnose import analyse, segments_markdown


def _gt_file(path, n=2000, hz=100, biases=True):
    t = (np.arange(n) * (1e9 / hz)).astype(np.int64) + 10**18
    s = np.arange(n) / hz
    p = np.stack([np.cos(0.2 * s), np.sin(0.2 * s), 0.1 * s], 1)
    v = np.stack([-0.2 * np.sin(0.2 * s), 0.2 * np.cos(0.2 * s), 0.1 + 0 * s], 1)
    q = Rotation.from_euler("z", 0.2 * s[:, None]).as_quat()[:, [3, 0, 1, 2]]
    bg = np.tile([0.01, -0.02, 0.005], (n, 1))
    ba = np.tile([0.1, 0.0, -0.05], (n, 1))
    rows = np.column_stack([p, q, v, bg, ba] if biases else [p, q, v, 0 * bg, 0 * ba])
    path.write_text("".join(f"{int(ti)}," + ",".join(f"{x:.12g}" for x in r) + "\n" for ti, r in zip(t, rows)))
    return t, p, q, v, bg, ba


def test_analyse_recovers_known_errors(tmp_path):
    t, p, q, v, bg, ba = _gt_file(tmp_path / "gt.csv")
    every = slice(0, None, 5)  # 20 Hz states
    # the estimate lives in a world frame rotated by 30 deg about z and shifted: alignment must undo it
    R = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    T = np.tile(np.eye(4), (len(t[every]), 1, 1))
    T[:, :3, 3] = (p[every] + [0.0, 0.0, 0.02]) @ R.T + [1.0, 2.0, 3.0]  # 2 cm constant error along z
    d = {"stamps_ns": t[every], "T_WS": T, "v_W": (v[every] + [0.05, 0, 0]) @ R.T, "bg": bg[every] + [0, 0, 0.003],
         "ba": ba[every], "status": ["tracking"] * len(T), "features_cam0": np.full(len(T), 80),
         "features_all": np.full(len(T), 200), "keyframes_ns": t[::50], "groundtruth": tmp_path / "gt.csv",
         "frames": len(T)}
    res = analyse(d, segment_s=5.0)
    np.testing.assert_allclose(res["rows"]["err_m"], 0.0, atol=1e-6)  # a constant offset is aligned away
    np.testing.assert_allclose(res["rows"]["vel_err_m_s"], 0.05, atol=1e-6)
    np.testing.assert_allclose(res["rows"]["bg_err_rad_s"], 0.003, atol=1e-9)
    np.testing.assert_allclose(res["rows"]["gt_deg_s"], np.degrees(0.2), rtol=1e-3)
    seg = res["segments"]
    assert len(seg) == 4 and abs(seg[0]["keyframes_per_s"] - 2.0) < 1e-9
    md = segments_markdown(res)
    assert md.count("\n| ") == 5 and "| 5 | 0.0000 | 0.050 | 3.00 | 0.000 | 1.000 | 80 | 2.0 | 11 | 0 |" in md
    # an estimate that travels 3 % short from 10 s on: the travel ratio says so there and only there
    late = t[every] >= t[0] + 10 * 10**9
    T[late, :3, 3] = T[late][0, :3, 3] + 0.97 * (T[late, :3, 3] - T[late][0, :3, 3])
    ratios = [s_["travel_ratio"] for s_ in analyse(d, segment_s=5.0)["segments"]]
    np.testing.assert_allclose(ratios, [1.0, 1.0, 0.97, 0.97], atol=1e-6)


def test_analyse_says_so_when_the_ground_truth_has_no_biases(tmp_path):
    """A replica of a sequence whose ground truth has no biases writes zeros: errors against them would be the
    estimated biases themselves (EuRoC's real gyro bias is ~80 mrad/s), so they are reported as unknown."""
    t, p, q, v, bg, ba = _gt_file(tmp_path / "gt.csv", n=600, biases=False)
    T = np.tile(np.eye(4), (len(t), 1, 1))
    T[:, :3, 3] = p
    d = {"stamps_ns": t, "T_WS": T, "v_W": v, "bg": bg, "ba": ba, "status": ["tracking"] * len(T),
         "features_cam0": np.full(len(T), 80), "features_all": np.full(len(T), 200), "keyframes_ns": t[::50],
         "groundtruth": tmp_path / "gt.csv", "frames": len(T)}
    res = analyse(d, segment_s=5.0)
    assert res["biases_known"] is False and np.all(np.isnan(res["rows"]["bg_err_rad_s"]))
    md = segments_markdown(res)
    assert "no biases" in md and "| 0 | 0.0000 | 0.000 | - | - | 1.000 | 80 |" in md
    _gt_file(tmp_path / "gt.csv", n=600)  # with biases: errors again
    assert analyse(d, segment_s=5.0)["biases_known"] is True
