import cv2
import numpy as np
import pytest

from shared.camera import (CalibrationError, CameraModel, camera_from_sensor_yaml, camera_to_sensor_yaml, load_rig,
                           read_sensor_yaml_file, stereo_rectification)
from shared.geometry import transform_points, inv_T
from shared.paths import euroc_dir

CALIB = euroc_dir() / "calib"  # the shared EuRoC folder, else the files bundled in data/euroc


def euroc_rig():
    return [camera_from_sensor_yaml(read_sensor_yaml_file(CALIB / f"{c}_sensor.yaml"), c) for c in ("cam0", "cam1")]


def random_points(n, seed=0):
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-0.6, 0.6, (n, 2)), np.ones(n)] * rng.uniform(0.5, 8.0, (n, 1))


def test_radtan_projection_matches_opencv_and_inverts():
    cam = euroc_rig()[0].camera
    assert cam.distortion == "radtan"
    p = random_points(500)
    uv, valid = cam.project(p)
    ref, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), cam.K, np.array(cam.dist_coeffs))
    np.testing.assert_allclose(uv, ref[:, 0], atol=1e-9)
    rays = cam.unproject(uv[valid])
    np.testing.assert_allclose(rays, p[valid] / p[valid, 2:3], atol=1e-9)
    ud = cam.undistort_points(uv[valid])
    np.testing.assert_allclose(ud, (p[valid, :2] / p[valid, 2:3]) * [cam.fx, cam.fy] + [cam.cx, cam.cy], atol=1e-6)


def test_equidistant_matches_opencv_fisheye():
    cam = CameraModel(640, 480, 300.0, 300.0, 320.0, 240.0, "equidistant", (-0.01, 0.02, -0.005, 0.001))
    p = random_points(300, 1)
    uv, _ = cam.project(p)
    ref, _ = cv2.fisheye.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, np.array(cam.dist_coeffs))
    np.testing.assert_allclose(uv, ref[:, 0], atol=1e-8)
    np.testing.assert_allclose(cam.unproject(uv), p / p[:, 2:3], atol=1e-9)


def test_behind_and_outside_are_invalid():
    cam = euroc_rig()[0].camera
    _, valid = cam.project(np.array([[0, 0, -1.0], [0, 0, 1.0], [10.0, 0, 1.0]]))
    assert valid.tolist() == [False, True, False]


def test_sensor_yaml_round_trip_and_errors(tmp_path):
    c0 = euroc_rig()[0]
    back = camera_from_sensor_yaml(camera_to_sensor_yaml(c0), "cam0")
    assert back.camera == c0.camera and np.allclose(back.T_SC, c0.T_SC)
    d = camera_to_sensor_yaml(c0)
    del d["intrinsics"]
    with pytest.raises(CalibrationError, match="intrinsics"):
        camera_from_sensor_yaml(d, "cam0")
    with pytest.raises(CalibrationError, match="distortion"):
        CameraModel(10, 10, 1, 1, 5, 5, "fancy")
    with pytest.raises(CalibrationError, match="not found"):
        load_rig(tmp_path / "nope.yaml")


def test_stereo_rectification_gives_horizontal_epipolar_lines():
    cam0, cam1 = euroc_rig()
    rect = stereo_rectification(cam0, cam1, (512, 384))
    assert 0.10 < rect.baseline_m < 0.12  # EuRoC baseline ~11 cm
    p_C0 = random_points(200, 3) + np.array([0, 0, 1.0])
    T_C1C0 = inv_T(cam1.T_SC) @ cam0.T_SC
    u0, v0 = cam0.camera.project(p_C0)
    u1, v1 = cam1.camera.project(transform_points(T_C1C0, p_C0))
    ok = v0 & v1
    # the rectified projections: rays of each camera rotated into N
    n0 = cam0.camera.unproject(u0[ok]) @ rect.R_C0N
    n1 = cam1.camera.unproject(u1[ok]) @ rect.R_C1N
    px0 = n0[:, :2] / n0[:, 2:3] * rect.K[0, 0] + rect.K[:2, 2]
    px1 = n1[:, :2] / n1[:, 2:3] * rect.K[0, 0] + rect.K[:2, 2]
    np.testing.assert_allclose(px0[:, 1], px1[:, 1], atol=1e-6)
    z_N = (p_C0[ok] @ rect.R_C0N)[:, 2]
    np.testing.assert_allclose(px0[:, 0] - px1[:, 0], rect.K[0, 0] * rect.baseline_m / z_N, rtol=1e-6)
    m0 = rect.maps0[0]
    assert m0.shape == (384, 512) and (m0 >= 0).mean() > 0.95
