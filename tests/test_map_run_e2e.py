"""Saved maps through ``sigmaslam run`` (real processes over Zenoh): a first run writes DIR/map/sparse.npz; a second
run over another stretch of the same flight in the same room, started with ``--map``, relocalises against it and
publishes in the first run's frame, so its poses match the ground truth under the first run's alignment alone;
``sigmaslam map info`` reads both maps; ``--localise-only`` writes no sparse map; a missing map is a clear error; a
run that never relocalises (in another room) still writes its trajectory, in its own frame ('odom'), and exits 0.

Reduced form (default): V1_02's real motion, 0-8 s mapped, 4-12 s localised (simulated IMU, the test box room).
``SIGMASLAM_E2E=full``: 0-20 s mapped, 10-30 s localised, real IMU."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

import e2e_dataset
from helpers_zenoh import REPO, child_env
from shared.euroc import read_trajectory, read_tum
from shared.metrics.ate import associate, compute_ate

FULL = os.environ.get("SIGMASLAM_E2E", "") == "full"


def _run(args, timeout=900):
    proc = subprocess.run([sys.executable, "-m", "services.app.cli", *args], cwd=REPO, env=child_env(),
                          capture_output=True, text=True, timeout=timeout)
    return proc.returncode, proc.stdout + proc.stderr


@pytest.mark.e2e
def test_a_second_run_localises_in_the_first_runs_map(tmp_path):
    (a0, a1), (b0, b1) = ((0.0, 20.0), (10.0, 30.0)) if FULL else ((0.0, 8.0), (4.0, 12.0))
    room = (min(a0, b0), max(a1, b1))
    data_a = e2e_dataset.make_dataset(tmp_path / "a", "V1_02", start_s=a0, seconds=a1 - a0, real_imu=FULL,
                                      room_span_s=room)
    data_b = e2e_dataset.make_dataset(tmp_path / "b", "V1_02", start_s=b0, seconds=b1 - b0, real_imu=FULL,
                                      room_span_s=room)
    common = ["--timeout-s", "600", "--settle-s", "5", "--set", "loop.min_age_s=3.0"]
    rc, log = _run(["run", str(data_a), "--out", str(tmp_path / "run_a"), *common])
    assert rc == 0, log[-3000:]
    assert (tmp_path / "run_a" / "map" / "sparse.npz").is_file(), log[-2000:]
    rc, info = _run(["map", "info", str(tmp_path / "run_a"), "--json"])
    assert rc == 0, info
    kf_a = json.loads(info)["sparse"]["keyframes"]
    assert kf_a > 10

    rc, log = _run(["run", str(data_b), "--out", str(tmp_path / "run_b"), "--map", str(tmp_path / "run_a"), *common])
    assert rc == 0, log[-3000:]
    stats = json.loads((tmp_path / "run_b" / "stats.json").read_text())
    loc = stats["localisation"]
    assert loc is not None and loc["time_to_relocalise_s"] is not None, (loc, log[-3000:])
    # tracking, loop.relocalise_settle_s (2 s), then two agreeing matches
    assert loc["time_to_relocalise_s"] < 0.75 * (b1 - b0), loc
    assert "relocalised" in log
    # the first run's alignment to the ground truth, applied to the second run's poses: in one frame
    gt = read_trajectory(data_a / "mav0" / "state_groundtruth_estimate0" / "data.csv")
    traj_a = read_tum(tmp_path / "run_a" / "trajectory_causal.txt")
    al = compute_ate(gt.stamps_ns, gt.p_WS, traj_a.stamps_ns, traj_a.p_WS, mode="se3").alignment
    gt_b = read_trajectory(data_b / "mav0" / "state_groundtruth_estimate0" / "data.csv")
    for name in ("trajectory_causal.txt", "trajectory_final.txt"):
        traj_b = read_tum(tmp_path / "run_b" / name)
        ia, ib = associate(gt_b.stamps_ns, traj_b.stamps_ns, 10_000_000)
        err = np.linalg.norm(gt_b.p_WS[ia] - al.apply(traj_b.p_WS[ib]), axis=1)
        assert len(err) > 20 and np.sqrt(np.mean(err ** 2)) < 0.15, (name, np.sqrt(np.mean(err ** 2)))
    # the second run's map is the first one extended
    rc, info = _run(["map", "info", str(tmp_path / "run_b"), "--json"])
    sparse = json.loads(info)["sparse"]
    assert sparse["keyframes"] > kf_a and len(sparse["sessions"]) == 2 and sparse["loop_edges"] >= 2, sparse

    # --localise-only: no map written; a missing map: exit 2 and the reason
    rc, log = _run(["run", str(data_b), "--out", str(tmp_path / "run_c"), "--map", str(tmp_path / "run_a"),
                    "--localise-only", *common, "--player-arg=--max-frames=120"])
    assert rc == 0, log[-3000:]
    assert not (tmp_path / "run_c" / "map" / "sparse.npz").exists()
    rc, log = _run(["run", str(data_b), "--out", str(tmp_path / "run_d"), "--map", str(tmp_path / "nothing")])
    assert rc == 2 and "no saved map" in log, log[-2000:]

    # a run that never relocalises (another room: nothing of the map in sight) keeps its trajectory, in its own frame
    data_e = e2e_dataset.make_dataset(tmp_path / "e", "V1_02", start_s=b0, seconds=4.0, real_imu=FULL, seed=7)
    rc, log = _run(["run", str(data_e), "--out", str(tmp_path / "run_e"), "--map", str(tmp_path / "run_a"), *common])
    assert rc == 0 and "never relocalised" in log, log[-3000:]
    text = (tmp_path / "run_e" / "trajectory_causal.txt").read_text()
    assert text.startswith("# frame: odom"), text[:200]
    stats = json.loads((tmp_path / "run_e" / "stats.json").read_text())
    assert stats["trajectory_frame"] == "odom" and stats["localisation"]["time_to_relocalise_s"] is None, stats
    traj_e = read_tum(tmp_path / "run_e" / "trajectory_causal.txt")
    assert len(traj_e.stamps_ns) >= 0.8 * stats["localisation"]["states_before_relocalisation"] > 40
    assert json.loads((tmp_path / "run_e" / "ate.json").read_text())["ate_rmse_m"] < 0.1
