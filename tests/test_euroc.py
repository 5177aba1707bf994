from pathlib import Path

import numpy as np
import pytest

from shared.euroc import (PoseSeries, TrajectoryFileError, read_euroc_csv, read_trajectory, read_tum,
                          write_euroc_csv, write_tum)

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "euroc"


def _series(n=10):
    rng = np.random.default_rng(0)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return PoseSeries(np.arange(n, dtype=np.int64) * 5_000_000 + 1_403_715_000_000_000_000,
                      rng.normal(size=(n, 3)), q)


def test_real_groundtruth():
    gt = read_euroc_csv(DATA / "groundtruth" / "V1_02_medium.state_groundtruth_estimate0.csv.xz")
    assert len(gt) > 10000 and gt.v_WS is not None
    dt = np.diff(gt.stamps_ns)
    assert abs(np.median(dt) - 5_000_000) < 1000  # 200 Hz
    np.testing.assert_allclose(np.linalg.norm(gt.q_WS_wxyz, axis=1), 1.0)


@pytest.mark.parametrize("fmt", ["tum", "csv"])
def test_roundtrip(tmp_path, fmt):
    s = _series()
    p = tmp_path / ("x.txt" if fmt == "tum" else "x.csv")
    (write_tum if fmt == "tum" else write_euroc_csv)(p, s)
    r = read_trajectory(p)
    np.testing.assert_array_equal(r.stamps_ns, s.stamps_ns)
    np.testing.assert_allclose(r.p_WS, s.p_WS, atol=1e-8)
    np.testing.assert_allclose(r.q_WS_wxyz, s.q_WS_wxyz, atol=1e-8)


def test_errors(tmp_path):
    with pytest.raises(TrajectoryFileError, match="not found"):
        read_tum(tmp_path / "nope.txt")
    bad = tmp_path / "bad.csv"
    bad.write_text("1,2,3\n")
    with pytest.raises(TrajectoryFileError, match="columns"):
        read_euroc_csv(bad)
    s = _series()
    p = tmp_path / "back.csv"
    write_euroc_csv(p, s)
    lines = p.read_text().splitlines()
    lines[4], lines[5] = lines[5], lines[4]
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(TrajectoryFileError, match="row 4"):
        read_euroc_csv(p)
