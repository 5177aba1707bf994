"""A small EuRoC-layout dataset for end-to-end tests: the real ground-truth motion of a EuRoC sequence (a
stretch of it), the real rig at reduced resolution, the test box room (tests/frontend_scene.py) sized
around the path, IMU simulated from the smoothed trajectory with the imu0 noise model (or the real IMU).

Not the production replica (services/app/synth): only fast enough to build inside a test.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

import frontend_scene as fs
from shared.camera import CameraCalib, camera_to_sensor_yaml
from shared.euroc import PoseSeries, read_euroc_csv
from services.app.datasets.euroc_writer import write_euroc
from services.app.synth.imu_sim import ImuNoise, read_imu_csv, simulate_imu
from shared.paths import euroc_files
from shared.rig import RigConfig, load_rig_config
from services.app.synth.trajectory import Trajectory


def scaled_rig(scale: float) -> list[CameraCalib]:
    """The real EuRoC rig with images scaled by ``scale`` (pixel centres kept consistent)."""
    out = []
    for c in load_rig_config(RigConfig()):
        m = c.camera
        cam = dataclasses.replace(m, width=int(round(m.width * scale)), height=int(round(m.height * scale)),
                                  fx=m.fx * scale, fy=m.fy * scale, cx=(m.cx + 0.5) * scale - 0.5,
                                  cy=(m.cy + 0.5) * scale - 0.5)
        out.append(dataclasses.replace(c, camera=cam))
    return out


def imu_clock(t0: int, t1: int, frames: np.ndarray, period_ns: int = 5_000_000) -> np.ndarray:
    """IMU stamps every ``period_ns`` from ``t0`` to ``t1``, the one nearest each frame moved onto the frame's stamp:
    on the real rig (EuRoC) an IMU sample is taken with every image, and a lockstep player sends it before the frame
    (IMU first on ties), so the frame's consumers need not wait for IMU up to its time."""
    stamps = np.arange(t0, t1, period_ns, dtype=np.int64)
    near = np.clip(np.round((frames - t0) / period_ns).astype(np.int64), 0, len(stamps) - 1)
    stamps[near] = frames
    return np.unique(stamps)


def make_dataset(out: str | Path, sequence: str = "V1_02", start_s: float = 0.0, seconds: float = 8.0,
                 scale: float = 0.5, real_imu: bool = False, seed: int = 0,
                 blank_s: tuple[float, float] | None = None, room_span_s: tuple[float, float] | None = None) -> Path:
    """Write the dataset to ``out``; frames within ``blank_s`` (seconds from the start) are black. The room is
    sized around the path of ``room_span_s`` (start, end in seconds of the sequence; default: this stretch), so
    that two stretches can share one room."""
    files = euroc_files(sequence)
    gt = read_euroc_csv(files["groundtruth"])
    # integer nanoseconds: a float64 near 1.4e18 ns is only good to 256 ns
    t0 = int(gt.stamps_ns[0]) + int(round(start_s * 1e9))
    t1 = t0 + int(round(seconds * 1e9))
    sel = (gt.stamps_ns >= t0 - 500_000_000) & (gt.stamps_ns <= t1 + 500_000_000)
    traj = Trajectory(PoseSeries(gt.stamps_ns[sel], gt.p_WS[sel], gt.q_WS_wxyz[sel]))
    frames = np.loadtxt(files["image_timestamps"], dtype=np.int64).reshape(-1)
    frames = frames[(frames >= t0 + 100_000_000) & (frames <= t1)]
    if real_imu:
        imu = read_imu_csv(files["imu"])
        keep = (imu.stamps_ns >= t0) & (imu.stamps_ns <= t1 + 50_000_000)
        imu_arr = np.c_[imu.stamps_ns[keep], imu.omega_S[keep], imu.acc_S[keep]]
    else:
        imu = simulate_imu(traj, imu_clock(t0, t1 + 50_000_000, frames), ImuNoise(), seed=seed, gyro_bias0=(0.002, -0.001, 0.003),
                           accel_bias0=(0.03, -0.02, 0.04))
        imu_arr = np.c_[imu.stamps_ns, imu.omega_S, imu.acc_S]
    gt_stamps = np.arange(t0, t1, 5_000_000, dtype=np.int64)
    p = traj.position(gt_stamps)
    p_room = p
    if room_span_s is not None:
        sel = (gt.stamps_ns >= gt.stamps_ns[0] + room_span_s[0] * 1e9) & (gt.stamps_ns <= gt.stamps_ns[0] + room_span_s[1] * 1e9)
        p_room = gt.p_WS[sel]
    room = fs.BoxRoom(lo=p_room.min(0) - [3.0, 3.0, 1.5], hi=p_room.max(0) + [3.0, 3.0, 1.5], seed=seed)
    cams = scaled_rig(scale)

    def frame_iter():
        for t in frames:
            if blank_s is not None and blank_s[0] <= (t - t0) * 1e-9 < blank_s[1]:
                yield int(t), [np.zeros((c.camera.height, c.camera.width), np.uint8) for c in cams]
                continue
            T = traj.pose(np.array([t]))[0]
            yield int(t), [fs.render(room, c, T) for c in cams]

    n = ImuNoise()
    imu_yaml = {"sensor_type": "imu", "rate_hz": 200, "gyroscope_noise_density": n.gyro_noise_density,
                "gyroscope_random_walk": n.gyro_random_walk, "accelerometer_noise_density": n.accel_noise_density,
                "accelerometer_random_walk": n.accel_random_walk,
                "T_BS": {"cols": 4, "rows": 4, "data": np.eye(4).ravel().tolist()}}
    q = traj.quaternion_wxyz(gt_stamps)
    write_euroc(out, {c.name: camera_to_sensor_yaml(c) for c in cams}, frame_iter(), imu_arr, imu_yaml,
                PoseSeries(gt_stamps, p, q))
    return Path(out)
