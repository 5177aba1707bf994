"""``sigmaslam eval ate``: reads TUM and EuRoC CSV, recovers a known rigid/similarity misalignment."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from helpers_zenoh import REPO, child_env
from shared.euroc import PoseSeries, write_euroc_csv, write_tum
from shared.geometry import R_to_quat_wxyz, so3_exp


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "services.app.cli", "eval", "ate", *args], cwd=REPO, env=child_env(),
                          capture_output=True, text=True, timeout=60)


def test_eval_ate_known_misalignment(tmp_path):
    rng = np.random.default_rng(0)
    n = 200
    stamps = (np.arange(n) * 50_000_000 + 10**18).astype(np.int64)
    p = np.cumsum(rng.normal(0, 0.05, (n, 3)), axis=0)
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    write_euroc_csv(tmp_path / "gt.csv", PoseSeries(stamps, p, q))
    R = so3_exp(np.array([0.3, -0.2, 1.0]))
    noise = rng.normal(0, 0.01, (n, 3))
    est = (p + noise) @ R.T * 1.5 + [1.0, 2.0, 3.0]  # rotated, scaled, shifted, 1 cm noise
    write_tum(tmp_path / "est.txt", PoseSeries(stamps, est, np.tile(R_to_quat_wxyz(R), (n, 1))))
    sim3 = json.loads(_cli("--gt", str(tmp_path / "gt.csv"), "--est", str(tmp_path / "est.txt"), "--mode", "sim3",
                           "--json").stdout)
    assert abs(sim3["scale"] - 1 / 1.5) < 1e-2 and sim3["matched"] == n
    assert 0.012 < sim3["ate_rmse_m"] < 0.022  # the noise (sqrt(3) cm), minus what the fit absorbs
    se3 = json.loads(_cli("--gt", str(tmp_path / "gt.csv"), "--est", str(tmp_path / "est.txt"), "--json").stdout)
    assert se3["ate_rmse_m"] > 5 * sim3["ate_rmse_m"]  # SE(3) cannot undo the scale
    bad = _cli("--gt", str(tmp_path / "missing.csv"), "--est", str(tmp_path / "est.txt"))
    assert bad.returncode == 1 and "not found" in bad.stdout
