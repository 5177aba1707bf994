"""A replica's twin with simulated IMU: same images and ground truth (linked), imu0 simulated from the ground
truth with the imu0 noise model of its sensor.yaml (``services.app.synth.imu_sim``), at the same IMU stamps.

    python -m tools.vio.sim_imu_variant SRC_REPLICA DST [--seed 0]

The images of a replica follow the smooth trajectory fitted to its ground truth; the ground truth written in the
replica samples that trajectory at 200 Hz, so a trajectory fitted to it again reproduces the rendered motion to
well below a millimetre, and the simulated IMU is consistent with the images.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import numpy as np

from shared.euroc import read_euroc_csv
from shared.euroc_reader import read_sensor_yaml
from services.app.synth.imu_sim import ImuNoise, read_imu_csv, simulate_imu
from services.app.synth.trajectory import Trajectory


def make_variant(src: Path, dst: Path, seed: int = 0) -> Path:
    s, d = Path(src) / "mav0", Path(dst) / "mav0"
    d.mkdir(parents=True, exist_ok=True)
    for child in s.iterdir():
        if child.name != "imu0" and not (d / child.name).exists():
            (d / child.name).symlink_to(child.resolve())
    gt = read_euroc_csv(s / "state_groundtruth_estimate0" / "data.csv")
    real = read_imu_csv(s / "imu0" / "data.csv")
    y = read_sensor_yaml(s / "imu0" / "sensor.yaml")
    noise = ImuNoise(float(y.get("gyroscope_noise_density", ImuNoise.gyro_noise_density)),
                     float(y.get("gyroscope_random_walk", ImuNoise.gyro_random_walk)),
                     float(y.get("accelerometer_noise_density", ImuNoise.accel_noise_density)),
                     float(y.get("accelerometer_random_walk", ImuNoise.accel_random_walk)))
    traj = Trajectory(gt, knot_spacing_s=0.05)
    stamps = real.stamps_ns[(real.stamps_ns >= traj.t0_ns) & (real.stamps_ns <= traj.t_end_ns)]
    imu = simulate_imu(traj, stamps, noise, seed=seed)
    (d / "imu0").mkdir(exist_ok=True)
    shutil.copy(s / "imu0" / "sensor.yaml", d / "imu0" / "sensor.yaml")
    with open(d / "imu0" / "data.csv", "w") as f:
        f.write("#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
                "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]\n")
        for t, w, a in zip(imu.stamps_ns, imu.omega_S, imu.acc_S):
            f.write(f"{int(t)}," + ",".join(f"{x:.9f}" for x in np.r_[w, a]) + "\n")
    return Path(dst)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("src")
    p.add_argument("dst")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args()
    print(make_variant(Path(a.src), Path(a.dst), a.seed))


if __name__ == "__main__":
    main()
