"""02: run the visual-inertial estimator in one process, without Zenoh, and measure its error.

Each process is a transport-free node: the frontend's ``FrontendNode`` (KLT tracking of both cameras, gyro-aided, and
the per-frame fast path: every frame's state against the back end's latest window) and the back end's
``BackendNode`` (a keyframe-window smoother in gtsam with IMU pre-integration, run at keyframes).
``tools/vio/offline.py`` runs them on the in-process runner (services/app/inprocess.py), which feeds a dataset in
the order the player would publish it (IMU samples and frames interleaved by stamp) and delivers each feature frame
to the fast path and the back end, the back end's window to the fast path and the fast path's state back to the
frontend, exactly as over ``frontend/frame``, ``estimator/window`` and ``estimator/state`` in a lockstep run. This
script calls it and reads the result: the causal trajectory (one pose per camera frame, never revised) and its
ATE against the replica's ground truth after SE(3) alignment (the paper's sec. V)::

    python -m examples.02_estimator_in_process                         # the default replica, first 10 s
    python -m examples.02_estimator_in_process --seconds 1.5           # a 1.5 s replica (rendered once)
    python -m examples.02_estimator_in_process --replica PATH --max-frames 0 --out out/vio
    python -m examples.02_estimator_in_process --set frontend.max_features_per_camera=150

The same run as processes over Zenoh is ``sigmaslam run DATASET --out DIR`` (docs/estimator.md); with loop closure
and the final bundle adjustment in one process it is ``python -m tools.eval_loop DATASET``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from services.app.synth.api import dataset_or_replica


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--replica", metavar="PATH", help="EuRoC ASL folder (default: the default replica)")
    ap.add_argument("--seconds", type=float, default=0.0, help="use a replica of the first S seconds of V1_02")
    ap.add_argument("--max-frames", type=int, default=200, help="camera frames to process (0: all; 200 = 10 s)")
    ap.add_argument("--config", help="YAML system config (default: the built-in defaults)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")
    ap.add_argument("--out", metavar="DIR", help="write the causal trajectory (TUM) here")
    args = ap.parse_args(argv)
    dataset = dataset_or_replica(args.replica, args.seconds)  # rendered on first use, then cached

    # 1. Run frontend + back end on the dataset. run() loads the system config (file + --set overrides, the same
    #    loader every service uses), takes the rig calibration from the dataset's sensor.yaml files, and returns
    #    per-stage timings, the ATE (when the folder has ground truth) and the causal trajectory.
    from tools.vio.offline import run

    print(f"estimating on {dataset} ({args.max_frames or 'all'} frames) ...", flush=True)
    res, traj = run(str(dataset), args.config, args.set, max_frames=args.max_frames)

    # 2. What came out. States with status 'initialising' (before the IMU allowed an initial attitude) are not
    #    part of the trajectory; 'tracking' states had visual landmarks, 'imu_only' ones did not.
    print(f"frames: {res['frames']}, poses: {res['poses']} ({res['status']})")
    print(f"per frame (median): frontend {res['frontend_median_ms']:.1f} ms, "
          f"fast path {res['fast_path_median_ms']:.1f} ms (CPU {res['cpu_frontend_median_ms']:.1f} + "
          f"{res['cpu_fast_path_median_ms']:.1f} ms); {res['window_optimisations']} window optimisations at "
          f"keyframes, {res['cpu_window_median_ms']:.1f} ms CPU each (median)")

    # 3. The trajectory is a PoseSeries: stamps_ns (int64), p_WS [m] and q_WS_wxyz (Hamilton, w first) in the
    #    estimator's world W (gravity-aligned, yaw and origin of the body at initialisation).
    if len(traj):
        travelled = float(np.linalg.norm(np.diff(traj.p_WS, axis=0), axis=1).sum())
        print(f"trajectory: {(traj.stamps_ns[-1] - traj.stamps_ns[0]) * 1e-9:.2f} s, {travelled:.2f} m travelled, "
              f"last p_W {np.round(traj.p_WS[-1], 3).tolist()}")

    # 4. Accuracy: RMSE of the position after the best rigid (SE(3)) alignment onto the ground truth.
    ate = res.get("ate_rmse_m")
    print(f"causal ATE (SE(3)): {ate:.4f} m" if ate is not None else "no ground truth: no ATE")

    if args.out:
        from shared.euroc import write_tum

        Path(args.out).mkdir(parents=True, exist_ok=True)
        write_tum(Path(args.out) / "trajectory_causal.txt", traj)
        print(f"wrote {Path(args.out) / 'trajectory_causal.txt'} (TUM: t x y z qx qy qz qw)")
    return {**res, "dataset": str(dataset)}


if __name__ == "__main__":
    main()
