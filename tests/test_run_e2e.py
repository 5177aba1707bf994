"""``sigmaslam run`` end to end on a small EuRoC-layout dataset: router, player (lockstep), frontend and
backend as real processes; trajectory files, stats.json and a causal ATE bound. A second of black frames in
the middle: IMU-only states, then tracking again, and no crash.

Reduced form (default): 7 s of V1_02's real motion in the test box room at half resolution, simulated IMU.
``SIGMASLAM_E2E=full``: 20 s of it with the real IMU, and the bundled 25 s V1_02 replica
(``services.app.synth.api.ensure_default_replica``, rendered if absent) with a causal ATE bound."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

import e2e_dataset
from helpers_zenoh import REPO, child_env
from shared.euroc import read_euroc_csv, read_tum

FULL = os.environ.get("SIGMASLAM_E2E", "") == "full"


@pytest.mark.e2e
def test_run_end_to_end_with_blank_second(tmp_path):
    seconds = 20.0 if FULL else 7.0
    data = e2e_dataset.make_dataset(tmp_path / "data", "V1_02", start_s=0.0, seconds=seconds, real_imu=FULL,
                                    blank_s=(4.0, 5.0))
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "services.app.cli", "run", str(data), "--out", str(out),
                           "--timeout-s", "600", "--settle-s", "5"], cwd=REPO, env=child_env(),
                          capture_output=True, text=True, timeout=900)
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log[-3000:]
    tum = read_tum(out / "trajectory_causal.txt")
    csv = read_euroc_csv(out / "trajectory_causal.csv")
    assert len(tum) == len(csv) > 0.9 * seconds * 20 - 15  # one pose per frame after initialisation
    assert np.array_equal(tum.stamps_ns, csv.stamps_ns)
    stats = json.loads((out / "stats.json").read_text())
    assert stats["states"].get("imu_only", 0) >= 10  # the black second
    assert stats["frontend_backend_median_ms"] > 0
    for svc, stage in (("frontend", "track"), ("backend", "optimise")):
        assert stats["services"][svc]["stages"][stage]["count"] >= len(tum)
    ate = json.loads((out / "ate.json").read_text())
    assert ate["ate_rmse_m"] < 0.05, ate
    assert "causal ATE" in log


@pytest.mark.e2e
@pytest.mark.skipif(not FULL, reason="long form only (SIGMASLAM_E2E=full)")
def test_run_default_replica(tmp_path):
    from services.app.synth.api import ensure_default_replica

    data = ensure_default_replica(progress=False)
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "services.app.cli", "run", str(data), "--out", str(out),
                           "--timeout-s", "1500"], cwd=REPO, env=child_env(), capture_output=True, text=True,
                          timeout=1800)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
    ate = json.loads((out / "ate.json").read_text())
    assert ate["ate_rmse_m"] < 0.05, ate  # measured 0.017 m in-process (docs/estimator.md)
    stats = json.loads((out / "stats.json").read_text())
    assert stats["states"].get("tracking", 0) > 450 and stats["states"].get("imu_only", 0) < 10
