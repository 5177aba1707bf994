"""Kalibr calibrations read into this project's rig: ``camchain-imucam.yaml`` (+ ``imu.yaml``).

Kalibr writes, per camera ``camN``: ``camera_model`` (pinhole), ``intrinsics`` [fu, fv, pu, pv],
``distortion_model`` (``radtan`` or ``equidistant``), ``distortion_coeffs``, ``resolution`` [w, h], ``rostopic``,
``T_cam_imu`` (4x4: IMU -> camera, i.e. T_CS, the camera's pose is its inverse), ``timeshift_cam_imu`` [s] with
t_imu = t_cam + timeshift. EuRoC's sensor.yaml holds T_BS = T_SC (the camera in the body = IMU frame), so
T_SC = inv(T_cam_imu). ``imu.yaml`` (``imu0``) holds the noise densities and random walks and ``update_rate``.

:func:`read_kalibr` gives the cameras as :class:`shared.camera.CameraCalib`, their topics and time shifts, and
the IMU's EuRoC-style sensor.yaml fields, so that a bag converted with it is an ordinary EuRoC folder.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from shared.camera import CalibrationError, CameraCalib, camera_from_sensor_yaml, read_sensor_yaml_file

DISTORTION = {"radtan": "radial-tangential", "equidistant": "equidistant", "none": "none"}
IMU_KEYS = ("gyroscope_noise_density", "gyroscope_random_walk", "accelerometer_noise_density", "accelerometer_random_walk")


@dataclass
class KalibrRig:
    cameras: list[CameraCalib]
    topics: list[str | None]  # the camera's rostopic, when Kalibr recorded it
    timeshift_ns: list[int]  # t_imu = t_cam + shift, per camera
    imu_yaml: dict = field(default_factory=dict)  # EuRoC imu0/sensor.yaml fields (empty without imu.yaml)
    imu_topic: str | None = None


def _matrix(value, what: str) -> np.ndarray:
    try:
        T = np.asarray(value, dtype=np.float64).reshape(4, 4)
    except (TypeError, ValueError):
        raise CalibrationError(f"{what}: not a 4x4 matrix") from None
    return T


def read_kalibr(camchain: str | Path, imu_calib: str | Path | None = None, rate_hz: float = 20.0) -> KalibrRig:
    """The rig of a Kalibr ``camchain-imucam.yaml`` (cameras in the order cam0, cam1, ...)."""
    p = Path(camchain)
    data = read_sensor_yaml_file(p)
    names = sorted((k for k in data if k.startswith("cam") and k[3:].isdigit()), key=lambda k: int(k[3:]))
    if not names:
        raise CalibrationError(f"{p}: no cam0/cam1/... entries: not a Kalibr camchain")
    cams, topics, shifts = [], [], []
    for n in names:
        c = data[n]
        where = f"{p} ({n})"
        if "T_cam_imu" not in c:
            raise CalibrationError(f"{where}: no T_cam_imu (a camchain.yaml without IMU? use camchain-imucam.yaml)")
        model = str(c.get("distortion_model", "none"))
        if model not in DISTORTION:
            raise CalibrationError(f"{where}: distortion_model {model!r} not supported (radtan, equidistant)")
        T_CS = _matrix(c["T_cam_imu"], f"{where} T_cam_imu")
        fields = {"T_BS": np.linalg.inv(T_CS).ravel().tolist(), "intrinsics": c.get("intrinsics"),
                  "resolution": c.get("resolution"), "camera_model": c.get("camera_model", "pinhole"),
                  "distortion_model": DISTORTION[model], "distortion_coefficients": c.get("distortion_coeffs", []),
                  "rate_hz": rate_hz}
        if fields["intrinsics"] is None or fields["resolution"] is None:
            raise CalibrationError(f"{where}: intrinsics and resolution are required")
        cams.append(camera_from_sensor_yaml(fields, n, where))
        topics.append(c.get("rostopic"))
        shifts.append(int(round(float(c.get("timeshift_cam_imu", 0.0)) * 1e9)))
    rig = KalibrRig(cams, topics, shifts)
    if imu_calib is not None:
        q = Path(imu_calib)
        imu = read_sensor_yaml_file(q)
        imu = imu.get("imu0", imu)
        missing = [k for k in IMU_KEYS if k not in imu]
        if missing:
            raise CalibrationError(f"{q}: missing {missing} (a Kalibr imu.yaml has them under imu0)")
        rig.imu_yaml = {"sensor_type": "imu", "comment": f"from {q.name}",
                        "T_BS": {"cols": 4, "rows": 4, "data": np.eye(4).ravel().tolist()},
                        "rate_hz": float(imu.get("update_rate", 200.0)), **{k: float(imu[k]) for k in IMU_KEYS}}
        rig.imu_topic = imu.get("rostopic")
    return rig
