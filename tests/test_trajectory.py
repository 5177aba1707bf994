import numpy as np

from shared.euroc import read_euroc_csv
from services.app.synth.trajectory import Trajectory, _quat_to_R, procedural
from shared.paths import euroc_dir

DATA = euroc_dir()  # the shared EuRoC folder, else the files bundled in data/euroc


def _rot_err(Ra, Rb):
    c = (np.trace(np.swapaxes(Ra, -1, -2) @ Rb, axis1=-2, axis2=-1) - 1) / 2
    return np.arccos(np.clip(c, -1, 1))


def test_real_groundtruth_residual():
    gt = read_euroc_csv(DATA / "groundtruth" / "V1_02_medium.state_groundtruth_estimate0.csv.xz")
    traj = Trajectory(gt)
    dp = np.linalg.norm(traj.position(gt.stamps_ns) - gt.p_WS, axis=1)
    dr = _rot_err(traj.rotation(gt.stamps_ns), _quat_to_R(gt.q_WS_wxyz))
    print(f"V1_02 spline residual: pos rms {np.sqrt(np.mean(dp**2))*1e3:.2f} mm max {dp.max()*1e3:.2f} mm; "
          f"rot rms {np.degrees(np.sqrt(np.mean(dr**2))):.3f} deg max {np.degrees(dr.max()):.3f} deg")
    assert np.sqrt(np.mean(dp**2)) < 5e-3 and np.degrees(np.sqrt(np.mean(dr**2))) < 0.3


def test_derivatives_match_finite_differences():
    traj = procedural("figure8")
    t = np.arange(1_500_000_000, 9_000_000_000, 137_000_000, dtype=np.int64)
    h = 100_000  # 0.1 ms
    v_fd = (traj.position(t + h) - traj.position(t - h)) / 2e-4
    np.testing.assert_allclose(traj.velocity(t), v_fd, atol=1e-6)
    a_fd = (traj.velocity(t + h) - traj.velocity(t - h)) / 2e-4
    np.testing.assert_allclose(traj.acceleration(t), a_fd, atol=1e-5)
    R0, R1 = traj.rotation(t - h), traj.rotation(t + h)
    dR = np.swapaxes(R0, -1, -2) @ R1
    w_fd = np.stack([dR[:, 2, 1] - dR[:, 1, 2], dR[:, 0, 2] - dR[:, 2, 0], dR[:, 1, 0] - dR[:, 0, 1]], -1) / 2 / 2e-4
    np.testing.assert_allclose(traj.body_rate(t), w_fd, atol=1e-5)


def test_static_is_static():
    traj = procedural("static")
    t = np.arange(1_100_000_000, 10_000_000_000, 50_000_000, dtype=np.int64)
    assert np.abs(traj.velocity(t)).max() < 1e-9
    assert np.abs(traj.body_rate(t)).max() < 1e-9


def test_series_from_matrices_round_trips_poses():
    from scipy.spatial.transform import Rotation

    from shared.euroc import series_from_matrices
    from shared.geometry import make_T, pose_from_pq

    R = Rotation.random(20, random_state=5).as_matrix()
    t = np.random.default_rng(5).normal(size=(20, 3))
    T = make_T(R, t)
    s = series_from_matrices(np.arange(20) * 5_000_000, T)
    assert s.stamps_ns.dtype == np.int64 and len(s) == 20
    np.testing.assert_allclose(pose_from_pq(s.p_WS, s.q_WS_wxyz), T, atol=1e-12)


def test_sparse_groundtruth_gets_a_determined_fit():
    """A 20 Hz ground truth (OpenVINS' vicon2gt of V1_01) is fitted with knots at least two samples apart instead of
    an underdetermined spline, and still follows the samples."""
    traj = procedural("figure8")
    stamps = np.arange(traj.t0_ns, traj.t_end_ns, 50_000_000, dtype=np.int64)
    from shared.euroc import PoseSeries
    gt = PoseSeries(stamps, traj.position(stamps), traj.quaternion_wxyz(stamps))
    fit = Trajectory(gt, knot_spacing_s=0.05)
    assert fit.knot_spacing_s >= 0.1 - 1e-9
    assert np.abs(fit.position(stamps) - gt.p_WS).max() < 5e-3
