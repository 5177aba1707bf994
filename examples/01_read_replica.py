"""01: read a replica, the data everything else runs on.

A *replica* is a synthetic copy of a real EuRoC sequence: the real trajectory, calibration, IMU readings and image
timestamps, with images rendered in a textured 3D scene whose exact mesh is the mapping ground truth. It is written
in the EuRoC ASL folder layout (``mav0/cam0``, ``mav0/cam1``, ``mav0/imu0``, ``mav0/state_groundtruth_estimate0``),
so the reader that serves a downloaded EuRoC sequence serves it too. The default replica (25 s of V1_02) is
rendered once on first use and cached under ``data/replicas/`` (or ``$SIGMASLAM_DATA/replicas``).

This script opens one with :class:`shared.euroc_reader.EurocDataset` and prints what a newcomer wants to know:
cameras and their calibration, frames, IMU, ground truth, and how the player interleaves them::

    python -m examples.01_read_replica                  # the default 25 s V1_02 replica (rendered once, ~minutes)
    python -m examples.01_read_replica --seconds 1.5    # a short replica of V1_02 (rendered once, cached)
    python -m examples.01_read_replica --replica PATH   # any EuRoC/ASL folder, real or replica

Conventions used below (docs/conventions.md): stamps are int64 nanoseconds, poses ``T_SC`` map camera points into
the body (IMU) frame S, quaternions are Hamilton in (w, x, y, z) order.
"""

from __future__ import annotations

import argparse
import itertools

import numpy as np

from services.app.synth.api import dataset_or_replica
from shared.camera import load_rig
from shared.euroc import read_trajectory
from shared.euroc_reader import EurocDataset
from shared.messages import ImuSample, MultiCameraFrame


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--replica", metavar="PATH", help="EuRoC ASL folder (default: the default replica)")
    ap.add_argument("--seconds", type=float, default=0.0, help="use a replica of the first S seconds of V1_02")
    args = ap.parse_args(argv)
    path = dataset_or_replica(args.replica, args.seconds)  # rendered on first use, then cached
    print(f"dataset: {path}")

    # 1. Open the folder. The reader checks every sensor.yaml and data.csv now, and synchronises the cameras by
    #    exact timestamp; problems it tolerates (missing images, backward stamps) are counted in ds.stats.
    ds = EurocDataset(path)

    # 2. The rig: one CameraCalib per camera, read from mav0/cam*/sensor.yaml (EuRoC calls T_SC "T_BS").
    rig = load_rig(path)
    for cam in rig:
        c = cam.camera
        # T_C0C = T_SC0^-1 T_SC: camera cam in the first camera's frame; its translation is the stereo baseline
        T_C0C = np.linalg.inv(rig[0].T_SC) @ cam.T_SC
        where = "" if cam is rig[0] else f", {np.linalg.norm(T_C0C[:3, 3]):.3f} m from {rig[0].name}"
        print(f"{cam.name}: {c.width}x{c.height} px, f = {c.fx:.1f} px, {c.distortion} distortion, "
              f"{cam.rate_hz:g} Hz{where}")

    # 3. Frames: the stamps of synchronised multi-camera frames, int64 ns.
    f = ds.frame_stamps_ns
    span_s = (f[-1] - f[0]) * 1e-9
    print(f"frames: {len(f)} over {span_s:.2f} s ({(len(f) - 1) / span_s:.1f} Hz)")

    # 4. IMU: gyro [rad/s] and accelerometer [m/s^2] in the body frame S. At rest the accelerometer reads
    #    gravity's reaction, ~9.81 m/s^2 pointing up.
    t_imu, imu = ds.imu_stamps_ns, ds.imu_values
    imu_hz = (len(t_imu) - 1) / ((t_imu[-1] - t_imu[0]) * 1e-9)
    acc_norm = float(np.linalg.norm(imu[: max(1, int(imu_hz / 2)), 3:], axis=1).mean())
    print(f"IMU: {len(t_imu)} samples at {imu_hz:.0f} Hz; |acc| over the first 0.5 s {acc_norm:.2f} m/s^2")

    # 5. Ground truth: the body pose T_WS at 200 Hz in the dataset's world frame (not the estimator's W: an
    #    evaluation aligns the two first, shared/metrics/ate.py).
    gt = read_trajectory(ds.groundtruth_path) if ds.groundtruth_path is not None else None
    if gt is not None:
        inside = (gt.stamps_ns >= f[0]) & (gt.stamps_ns <= f[-1])
        p = gt.p_WS[inside]
        length = float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())
        print(f"ground truth: {len(gt)} poses, {int(inside.sum())} within the frames' span; "
              f"path length {length:.2f} m; first q_WS_wxyz {np.round(gt.q_WS_wxyz[0], 3).tolist()}")
    scene = ds.root / "scene" / "mesh.ply"
    print(f"scene mesh (mapping ground truth): {scene if scene.is_file() else 'none (a real sequence)'}")

    # 6. Replay order: messages() yields ImuSample and MultiCameraFrame in time order, as the player publishes
    #    them on sensors/imu and sensors/frame. Count the IMU samples between the first frames.
    first = None
    imu_between: list[int] = []
    n = 0
    for msg in itertools.islice(ds.messages(), 0, 400):
        if isinstance(msg, ImuSample):
            n += 1
        elif isinstance(msg, MultiCameraFrame):
            if first is None:
                first = msg
            else:
                imu_between.append(n)
            n = 0
    img = first.images[0]
    print(f"first frame: {first.camera_names}, image {img.shape} {img.dtype}, mean grey {img.mean():.0f}; "
          f"IMU samples between frames {imu_between[:5]}")
    print(f"reader counters: {ds.stats}")
    return {"path": str(path), "cameras": [c.name for c in rig], "frames": int(len(f)), "span_s": float(span_s),
            "imu_samples": int(len(t_imu)), "imu_hz": float(imu_hz), "acc_norm": acc_norm,
            "gt_poses": 0 if gt is None else len(gt), "scene_mesh": scene.is_file(), "imu_between": imu_between,
            "image_shape": tuple(img.shape)}


if __name__ == "__main__":
    main()
