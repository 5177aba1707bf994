"""Mono-inertial estimation (rig.cameras=[cam0]): still detection against known rotations, and the frontend +
back end on a short EuRoC-motion dataset with the real IMU (a still start with rotors running, then take-off)
tracking against ground truth, where the IMU alone drifts by metres."""

import numpy as np
import pytest

import e2e_dataset
from services.backend.window.still import bearing_rotation, still_motion
from shared.geometry import so3_exp
from tools.vio.offline import run


def _bearings(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    f = np.c_[rng.uniform(-0.6, 0.6, (n, 2)), np.ones(n)]
    return f / np.linalg.norm(f, axis=1, keepdims=True)


def test_bearing_rotation_recovers_a_known_rotation():
    R = so3_exp(np.array([0.01, -0.02, 0.015]))
    f_a = _bearings(50)
    np.testing.assert_allclose(bearing_rotation(f_a, f_a @ R.T), R, atol=1e-12)


def test_still_motion_measures_small_rotation_and_rejects_motion():
    f = 458.0
    R_SC = so3_exp(np.array([0.0, 0.0, np.pi / 2]))  # camera axes turned in the body
    f_kf = _bearings(60, 1)
    xy_kf = f_kf[:, :2] / f_kf[:, 2:]
    R_CnCk = so3_exp(np.array([0.0, 0.0006, 0.0]))  # ~0.3 px of image motion
    p_n = f_kf @ R_CnCk.T
    xy_n = p_n[:, :2] / p_n[:, 2:]
    still = still_motion(xy_kf, xy_n, f, R_SC, 1.0, 20)
    assert still is not None and still.num_features == 60 and still.median_flow_px < 0.5
    np.testing.assert_allclose(still.R_SkSn, R_SC @ R_CnCk.T @ R_SC.T, atol=1e-9)
    # a translation of 2 cm at depths of 2-4 m moves the image by a few pixels: not still
    depth = np.random.default_rng(2).uniform(2.0, 4.0, 60)
    p = f_kf / f_kf[:, 2:] * depth[:, None] - np.array([0.02, 0.0, 0.0])
    assert still_motion(xy_kf, p[:, :2] / p[:, 2:], f, R_SC, 1.0, 20) is None
    assert still_motion(xy_kf[:10], xy_n[:10], f, R_SC, 1.0, 20) is None  # too few features to tell


@pytest.mark.e2e  # the frontend and back end over 9 s of rendered frames (~25 s)
def test_mono_vio_tracks_a_still_start_and_take_off(tmp_path):
    # V1_02 from 1 s: 2 s standing on the ground with the rotors running, then take-off (real IMU)
    data = e2e_dataset.make_dataset(tmp_path / "data", "V1_02", start_s=1.0, seconds=9.0, real_imu=True)
    res, traj = run(str(data), None, ["rig.cameras=[cam0]"])
    assert res["poses"] > 150  # all but the first 0.5 s (IMU for the initialisation)
    # the same run without the still factors (the state before mono support) drifts by metres
    print(res)
    assert res["ate_rmse_m"] < 0.15, res
    assert res["status"]["tracking"] > 0.5 * res["poses"], res


def test_alignment_recovers_scale_velocities_and_gravity():
    """Keyframes of a known accelerating, turning motion: camera centres divided by an unknown scale, the exact
    IMU deltas between them; the linear alignment returns the scale, every velocity and gravity."""
    from services.backend.window.mono_init import align

    rng = np.random.default_rng(3)
    g = np.array([0.3, -0.2, -9.79])  # in the first camera's frame (tilted)
    K, h = 6, 0.4
    R_0S = [so3_exp(rng.normal(0, 0.2, 3))]
    p, v = [np.zeros(3)], [rng.normal(0, 0.5, 3)]
    a_W = rng.normal(0, 1.0, (K, 3))  # piecewise-constant acceleration in the frame of the first camera
    dp, dv = [], []
    for k in range(K - 1):
        # body-frame deltas of gtsam's pre-integration for a constant acceleration a_W over h
        dv.append(R_0S[k].T @ (a_W[k] * h))
        dp.append(R_0S[k].T @ (0.5 * a_W[k] * h * h))
        p.append(p[k] + v[k] * h + 0.5 * (a_W[k] + g) * h * h)
        v.append(v[k] + (a_W[k] + g) * h)
        R_0S.append(R_0S[k] @ so3_exp(rng.normal(0, 0.1, 3)))
    R_0S = np.array(R_0S)
    t_SC = np.array([-0.02, 0.06, 0.01])
    scale = 2.5
    c_0 = (np.array(p) + R_0S @ t_SC) / scale  # up-to-scale camera centres
    s, v_est, g_est = align(R_0S, c_0, t_SC, np.array(dp), np.array(dv), np.full(K - 1, h), float(np.linalg.norm(g)))
    assert s == pytest.approx(scale, rel=1e-6)
    np.testing.assert_allclose(v_est, np.array(v), atol=1e-6)
    np.testing.assert_allclose(g_est, g, atol=1e-6)

