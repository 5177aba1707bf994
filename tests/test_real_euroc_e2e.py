"""``sigmaslam run`` on real EuRoC frames, as a user with a downloaded sequence runs it: the demo's services
(frontend, back end, depth, mapping; the viewer left out, it would take the fixed port 8080) as processes, on
``$SIGMASLAM_SHARED/data/real/euroc_V1_01_micro`` (V1_01_easy: the first 60 real stereo pairs, 3 s at 20 Hz,
the MAV standing on the ground; see data/real/README.md there). Skipped when that folder is absent.

The folder has the quirks of a trimmed download, which ``run`` must cope with by itself: the IMU covers the
whole 145 s sequence (the player plays only the frames' span, ``player.imu_margin_s``), and the ground truth
is a TUM file at the folder's top, ``groundtruth_tum.txt``, not ``mav0/state_groundtruth_estimate0/data.csv``,
starting 1.04 s after the first image (the ATE covers the overlap only). The command is the documented form,
``sigmaslam run DATASET --out DIR CONFIG``, in lockstep (the player waits for each state: about 10-20 s on 2 cores).

What is asserted (the figures measured are printed; run with ``-s``):

(a) tracking: the back end initialises within the first second and every state after that is 'tracking'
    (never 'lost' or 'reset'; at most 10% 'imu_only'), one causal pose per frame after initialisation;
(b) drift against the ground truth over the static span, two ways, each under 2 cm:
    - the ATE that ``run`` writes (ate.json: SE(3) alignment over the poses with ground truth within 10 ms, i.e.
      the 1.9 s overlap), which must have found the root TUM file by itself;
    - alignment-free drift: the estimate's displacement from its first pose that has ground truth, rotated
      into the ground truth's world by the orientations of that one pose (both are the body = IMU pose), minus
      the ground truth's own displacement, at every later matched time; the maximum. An SE(3) fit over a
      nearly static span can absorb a slow slide; anchoring at the first pose cannot. The ground truth itself
      moves 2.6 mm in that span (Vicon noise, the MAV nudged), so this is the estimator's drift.
    Also the estimate's largest displacement from its first pose over its whole span, including the half second
    before the ground truth starts, stays under 3 cm: the MAV stands still (its ground truth moves 6 mm over
    all of its 4 s), but for the first second after initialisation the causal pose slides up to 1.4 cm between
    keyframes and snaps back at each (presumably while the accelerometer bias settles; 13.6 mm in nearly every
    run, 19.8 mm once, pinned to one core from a cold start), a transient mostly before the ground truth starts.
(c) mapping: DIR/mesh.ply has vertices and triangles, integrated from at least one posed depth frame, and lies
    within the Vicon room around the trajectory (every 50th vertex within 10 m of it).
"""

from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
import pytest

from helpers_zenoh import REPO, child_env
from shared.euroc import read_euroc_csv, read_tum
from shared.geometry import quat_wxyz_to_R
from shared.metrics.ate import associate

SERVICES = "supervisor.services=[{name: frontend, argv: [frontend]}, {name: backend, argv: [backend]}, " \
           "{name: depth, argv: [depth]}, {name: mapping, argv: [mapping]}]"  # configs/demo.yaml's, no viewer
FRAMES = 60
LIMIT_M = 0.02


@pytest.mark.e2e
def test_run_on_real_euroc_frames(tmp_path, real_data):
    micro = real_data("euroc_V1_01_micro", "mav0")  # skipped without it
    out = tmp_path / "v101"
    t0 = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "services.app.cli", "run", str(micro), "--out", str(out),
                           str(REPO / "configs" / "demo.yaml"), "--set", SERVICES, "--timeout-s", "300"],
                          cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=600)
    wall = time.monotonic() - t0
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log[-4000:]
    assert f"player: {FRAMES} frames sent" in log and "imu_outside_frames" in log, log[-4000:]

    # (a) tracking after initialisation
    stats = json.loads((out / "stats.json").read_text())
    states = stats["states"]
    assert stats["frames_sent"] == FRAMES and sum(states.values()) == FRAMES, states
    init = states.get("initialising", 0)
    after = FRAMES - init
    assert init <= 20, states  # initialised within the first second
    assert not states.get("lost") and not states.get("reset"), states
    assert states.get("tracking", 0) >= 0.9 * after and states.get("tracking", 0) + states.get("imu_only", 0) == after
    est = read_tum(out / "trajectory_causal.txt")
    assert len(est) == after and np.array_equal(est.stamps_ns, read_euroc_csv(out / "trajectory_causal.csv").stamps_ns)

    # (b) drift against the ground truth, over the span both cover
    gt_path = micro / "groundtruth_tum.txt"
    ate = json.loads((out / "ate.json").read_text())
    assert ate["groundtruth"] == str(gt_path), ate  # found by itself, no --gt
    assert 30 <= ate["matched"] < ate["poses"] == after, ate  # the overlap only: ground truth starts 1.04 s late
    assert ate["ate_rmse_m"] < LIMIT_M and ate["non_causal"]["ate_rmse_m"] < LIMIT_M, ate
    gt = read_tum(gt_path)
    ie, ig = associate(est.stamps_ns, gt.stamps_ns, 10_000_000)
    assert len(ie) == ate["matched"]
    R_Wgt_West = quat_wxyz_to_R(gt.q_WS_wxyz[ig[0]]) @ quat_wxyz_to_R(est.q_WS_wxyz[ie[0]]).T
    d_est = (est.p_WS[ie] - est.p_WS[ie[0]]) @ R_Wgt_West.T
    d_gt = gt.p_WS[ig] - gt.p_WS[ig[0]]
    drift = np.linalg.norm(d_est - d_gt, axis=1)
    whole = np.linalg.norm(est.p_WS - est.p_WS[0], axis=1)

    # (c) the mesh
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(out / "mesh.ply"))
    vertices = np.asarray(mesh.vertices)
    mapping = json.loads((out / "mapping.json").read_text())
    near = np.min(np.linalg.norm(vertices[::50, None, :] - est.p_WS[None, ::5, :], axis=2), axis=1)

    integrated = mapping["counts"].get("integrated", 0)
    print(f"\nreal EuRoC V1_01 micro: {wall:.1f} s wall; states {states}; {len(est)} causal poses; "
          f"ATE causal {ate['ate_rmse_m'] * 1000:.1f} mm, non-causal {ate['non_causal']['ate_rmse_m'] * 1000:.1f} "
          f"mm over {ate['matched']} poses; anchored drift max {drift.max() * 1000:.1f} mm (ground truth moved "
          f"{np.linalg.norm(d_gt, axis=1).max() * 1000:.1f} mm); estimate's largest displacement "
          f"{whole.max() * 1000:.1f} mm; mesh {len(vertices)} vertices, {len(mesh.triangles)} triangles from "
          f"{integrated} depth frames ({(out / 'mesh.ply').stat().st_size / 1e6:.1f} MB)")
    assert drift.max() < LIMIT_M and whole.max() < 1.5 * LIMIT_M
    assert len(vertices) > 100 and len(mesh.triangles) > 100 and integrated >= 1
    assert near.max() < 10.0
