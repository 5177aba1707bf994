import gtsam
import numpy as np

from shared.euroc import read_euroc_csv
from services.app.synth.imu_sim import G_W, ImuNoise, read_imu_csv, simulate_imu, time_offset
from services.app.synth.trajectory import Trajectory, procedural
from shared.paths import euroc_dir

DATA = euroc_dir()  # the shared EuRoC folder, else the files bundled in data/euroc


def _gt():
    return Trajectory(read_euroc_csv(DATA / "groundtruth" / "V1_02_medium.state_groundtruth_estimate0.csv.xz"))


def test_real_imu_alignment_and_gravity():
    traj = _gt()
    imu = read_imu_csv(DATA / "imu" / "V102.imu0_data.csv.xz")
    d, _, corr = time_offset(traj, imu)
    print(f"best offset {d / 1e6:.1f} ms corr {corr.max():.3f}")
    assert abs(d) <= 5_000_000 and corr.max() > 0.8
    # static start: mean real accel vs R_WS^T (0,0,9.81)
    t = imu.stamps_ns[(imu.stamps_ns > traj.t0_ns) & (imu.stamps_ns < traj.t0_ns + 500_000_000)]
    pred = np.einsum("nji,j->ni", traj.rotation(t), -G_W).mean(0)
    real = imu.acc_S[np.isin(imu.stamps_ns, t)].mean(0)
    print("static accel real", real, "predicted", pred)
    assert np.linalg.norm(real - pred) < 0.3


def test_noise_statistics():
    traj = procedural("static")
    t = traj.t0_ns + np.arange(1000, dtype=np.int64) * 5_000_000
    imu = simulate_imu(traj, t, ImuNoise(), seed=1)
    w = imu.omega_S - imu.gyro_bias
    np.testing.assert_allclose(w.std(0), 1.6968e-04 * np.sqrt(200), rtol=0.15)
    again = simulate_imu(traj, t, ImuNoise(), seed=1)
    np.testing.assert_array_equal(again.acc_S, imu.acc_S)


def test_preintegration_reproduces_relative_poses():
    traj = _gt()
    cam = np.loadtxt(DATA / "image_timestamps" / "V102.txt", dtype=np.int64)
    cam = cam[(cam > traj.t0_ns + 10**9) & (cam < traj.t_end_ns - 10**9)][100:160]
    t_imu = np.arange(cam[0], cam[-1] + 1, 5_000_000, dtype=np.int64)
    t_all = np.union1d(t_imu, cam)
    params = gtsam.PreintegrationParams.MakeSharedU(9.81)
    params.setGyroscopeCovariance(np.eye(3) * 1e-8)
    params.setAccelerometerCovariance(np.eye(3) * 1e-8)
    params.setIntegrationCovariance(np.eye(3) * 1e-8)
    worst_r = worst_p = 0.0
    for a, b in zip(cam[:-1], cam[1:]):
        pim = gtsam.PreintegratedImuMeasurements(params, gtsam.imuBias.ConstantBias())
        idx = np.nonzero((t_all >= a) & (t_all < b))[0]
        for i in idx:  # midpoint sample of each interval for second-order accuracy
            dt = (t_all[i + 1] - t_all[i]) * 1e-9
            tm = np.array([(t_all[i] + t_all[i + 1]) // 2])
            m = simulate_imu(traj, tm)
            pim.integrateMeasurement(m.acc_S[0], m.omega_S[0], dt)
        Ta, Tb = traj.pose(np.array([a, b]))
        state = gtsam.NavState(gtsam.Rot3(Ta[:3, :3]), Ta[:3, 3], traj.velocity(np.array([a]))[0])
        pred = pim.predict(state, gtsam.imuBias.ConstantBias())
        worst_r = max(worst_r, np.linalg.norm(gtsam.Rot3.Logmap(pred.attitude().between(gtsam.Rot3(Tb[:3, :3])))))
        worst_p = max(worst_p, np.linalg.norm(pred.position() - Tb[:3, 3]))
    print(f"preintegration residual over 50 ms: rot {worst_r:.2e} rad, pos {worst_p * 1e3:.4f} mm")
    assert worst_r < 1e-4 and worst_p < 1e-3
