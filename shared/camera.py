"""Camera models and rig calibration: pinhole with radial-tangential or equidistant distortion.

Axes are OpenCV's (x right, y down, z forward). Everything is vectorised over points:

- ``project(p_C (N,3)) -> uv (N,2), valid (N,)``: 3D points in the camera frame to distorted pixels;
- ``unproject(uv (N,2)) -> rays (N,3)``: distorted pixels to rays with z = 1 (x/z, y/z, 1);
- ``undistort_points(uv) -> uv'``: distorted pixels to the ideal pinhole pixels of the same K;
- ``remap_to_pinhole(K_new, size, R_CN)``: maps for ``cv2.remap`` that resample the image into a
  distortion-free pinhole camera N rotated by ``R_CN`` (undistortion and stereo rectification).

Distortion models (as in the EuRoC/Kalibr sensor.yaml): ``radtan`` (k1, k2, p1, p2), ``equidistant``
(k1..k4, Kannala-Brandt on the incidence angle), ``none``. The rig is a list of :class:`CameraCalib`
(model, ``T_SC`` camera-to-body extrinsic, rate), read from EuRoC ``sensor.yaml`` files.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import yaml

from shared.geometry import inv_T

DISTORTION_MODELS = {"none": 0, "radtan": 4, "radial-tangential": 4, "equidistant": 4}


class CalibrationError(ValueError):
    """Missing or malformed calibration; the message names the file and the key."""


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics of one camera. ``width``/``height`` [px]; ``fx, fy, cx, cy`` [px]."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: str = "none"  # 'none' | 'radtan' | 'equidistant'
    dist_coeffs: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        model = "radtan" if self.distortion == "radial-tangential" else self.distortion
        if model not in DISTORTION_MODELS:
            raise CalibrationError(f"unknown distortion model {self.distortion!r} (radtan, equidistant, none)")
        object.__setattr__(self, "distortion", model)
        coeffs = tuple(float(c) for c in self.dist_coeffs) or (0.0,) * DISTORTION_MODELS[model]
        if len(coeffs) != DISTORTION_MODELS[model]:
            raise CalibrationError(f"{model} needs {DISTORTION_MODELS[model]} coefficients, got {len(coeffs)}")
        object.__setattr__(self, "dist_coeffs", coeffs)
        if self.width <= 0 or self.height <= 0 or self.fx <= 0 or self.fy <= 0:
            raise CalibrationError(f"bad intrinsics/resolution: {self}")

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) as OpenCV wants it."""
        return (self.width, self.height)

    def pinhole(self) -> "CameraModel":
        """The same intrinsics without distortion."""
        return replace(self, distortion="none", dist_coeffs=())

    # ---------------------------------------------------------------- distortion on normalised coords
    def distort(self, xn: np.ndarray) -> np.ndarray:
        """Ideal normalised coordinates (N,2) -> distorted normalised coordinates (N,2)."""
        xn = np.asarray(xn, dtype=np.float64)
        if self.distortion == "none":
            return xn.copy()
        x, y = xn[:, 0], xn[:, 1]
        r2 = x * x + y * y
        if self.distortion == "radtan":
            k1, k2, p1, p2 = self.dist_coeffs
            radial = 1.0 + k1 * r2 + k2 * r2 * r2
            return np.stack([x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                             y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y], axis=1)
        r = np.sqrt(r2)
        theta = np.arctan(r)
        scale = np.where(r > 1e-12, self._theta_d(theta) / np.maximum(r, 1e-12), 1.0)
        return xn * scale[:, None]

    def _theta_d(self, theta: np.ndarray) -> np.ndarray:
        k1, k2, k3, k4 = self.dist_coeffs
        t2 = theta * theta
        return theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))

    def undistort_normalised(self, xd: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Distorted normalised coordinates (N,2) -> ideal ones (inverse of :meth:`distort`, Newton)."""
        xd = np.asarray(xd, dtype=np.float64)
        if self.distortion == "none":
            return xd.copy()
        if self.distortion == "equidistant":
            rd = np.linalg.norm(xd, axis=1)
            theta = rd.copy()
            k1, k2, k3, k4 = self.dist_coeffs
            for _ in range(iterations):
                t2 = theta * theta
                f = self._theta_d(theta) - rd
                df = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
                theta = theta - f / df
            theta = np.clip(theta, 0.0, np.pi / 2 - 1e-6)
            scale = np.where(rd > 1e-12, np.tan(theta) / np.maximum(rd, 1e-12), 1.0)
            return xd * scale[:, None]
        k1, k2, p1, p2 = self.dist_coeffs
        xn = xd.copy()
        for _ in range(iterations):  # Gauss-Newton with the analytic 2x2 Jacobian of distort()
            x, y = xn[:, 0], xn[:, 1]
            r2 = x * x + y * y
            radial = 1.0 + k1 * r2 + k2 * r2 * r2
            dr = 2 * k1 + 4 * k2 * r2  # d radial / d(r2) * 2
            res = self.distort(xn) - xd
            j11 = radial + x * dr * x + 2 * p1 * y + 6 * p2 * x
            j12 = x * dr * y + 2 * p1 * x + 2 * p2 * y
            j21 = y * dr * x + 2 * p1 * x + 2 * p2 * y
            j22 = radial + y * dr * y + 6 * p1 * y + 2 * p2 * x
            det = j11 * j22 - j12 * j21
            det = np.where(np.abs(det) < 1e-12, 1e-12, det)
            xn = xn - np.stack([(j22 * res[:, 0] - j12 * res[:, 1]) / det,
                                (-j21 * res[:, 0] + j11 * res[:, 1]) / det], axis=1)
        return xn

    # ---------------------------------------------------------------- pixels and 3D points
    def project(self, p_C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Points (N,3) in C -> distorted pixels (N,2) and a mask of points in front and inside the image."""
        p = np.asarray(p_C, dtype=np.float64).reshape(-1, 3)
        z = p[:, 2]
        front = z > 1e-6
        xn = p[:, :2] / np.where(front, z, 1.0)[:, None]
        xd = self.distort(xn)
        uv = np.stack([self.fx * xd[:, 0] + self.cx, self.fy * xd[:, 1] + self.cy], axis=1)
        inside = (uv[:, 0] >= -0.5) & (uv[:, 0] <= self.width - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= self.height - 0.5)
        return uv, front & inside & np.isfinite(uv).all(axis=1)

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels (N,2) -> rays (N,3) in C with z = 1."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        xd = np.stack([(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy], axis=1)
        xn = self.undistort_normalised(xd)
        return np.concatenate([xn, np.ones((len(xn), 1))], axis=1)

    def undistort_points(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels (N,2) -> pixels of the distortion-free camera with the same K."""
        r = self.unproject(uv)
        return np.stack([self.fx * r[:, 0] + self.cx, self.fy * r[:, 1] + self.cy], axis=1)

    def pixel_grid(self) -> np.ndarray:
        """(H*W, 2) pixel centres in row-major order (u = column, v = row)."""
        v, u = np.mgrid[0:self.height, 0:self.width]
        return np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)

    def remap_to_pinhole(self, K_new: np.ndarray, size: tuple[int, int],
                         R_CN: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``cv2.remap`` maps (float32 (h,w) each) from this camera's image to a pinhole camera N.

        N has intrinsics ``K_new`` and image ``size`` = (w, h); its axes are ``R_CN`` (N -> C) rotated from C.
        """
        w, h = size
        v, u = np.mgrid[0:h, 0:w]
        pix = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1).astype(np.float64)
        rays_N = pix @ np.linalg.inv(np.asarray(K_new, float)).T
        rays_C = rays_N if R_CN is None else rays_N @ np.asarray(R_CN, float).T
        uv, valid = self.project(rays_C)
        uv[~valid] = -1.0
        return uv[:, 0].reshape(h, w).astype(np.float32), uv[:, 1].reshape(h, w).astype(np.float32)


@dataclass(frozen=True)
class CameraCalib:
    """One camera of the rig: its model, its extrinsic ``T_SC`` (camera to body/IMU) and frame rate."""

    name: str
    camera: CameraModel
    T_SC: np.ndarray = field(default_factory=lambda: np.eye(4))
    rate_hz: float = 20.0


def camera_from_sensor_yaml(data: dict, name: str, source: str = "<dict>") -> CameraCalib:
    """A camera from the fields of an EuRoC/Kalibr ``sensor.yaml`` (T_BS, intrinsics, resolution, ...)."""
    try:
        fu, fv, cu, cv = (float(x) for x in data["intrinsics"])
        width, height = (int(x) for x in data["resolution"])
        tbs = data["T_BS"]
        T = np.asarray(tbs["data"] if isinstance(tbs, dict) else tbs, dtype=np.float64).reshape(4, 4)
    except KeyError as e:
        raise CalibrationError(f"{source}: missing key {e.args[0]!r}") from None
    except (TypeError, ValueError) as e:
        raise CalibrationError(f"{source}: malformed camera calibration ({e})") from None
    if data.get("camera_model", "pinhole") != "pinhole":
        raise CalibrationError(f"{source}: camera_model {data['camera_model']!r} not supported (pinhole)")
    model = CameraModel(width, height, fu, fv, cu, cv, str(data.get("distortion_model", "none")),
                        tuple(data.get("distortion_coefficients", ()) or ()))
    if not np.allclose(T[3], [0, 0, 0, 1]) or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-5):
        raise CalibrationError(f"{source}: T_BS is not a rigid transform")
    return CameraCalib(name, model, T, float(data.get("rate_hz", 20.0)))


def camera_to_sensor_yaml(calib: CameraCalib) -> dict:
    """Inverse of :func:`camera_from_sensor_yaml` (the fields a writer puts in sensor.yaml)."""
    c = calib.camera
    return {"sensor_type": "camera", "comment": calib.name,
            "T_BS": {"cols": 4, "rows": 4, "data": [float(x) for x in np.asarray(calib.T_SC).ravel()]},
            "rate_hz": calib.rate_hz, "resolution": [c.width, c.height], "camera_model": "pinhole",
            "intrinsics": [c.fx, c.fy, c.cx, c.cy],
            "distortion_model": "radial-tangential" if c.distortion == "radtan" else c.distortion,
            "distortion_coefficients": list(c.dist_coeffs)}


def write_rig_yaml(path: str | Path, cameras: list[CameraCalib], comment: str = "") -> Path:
    """A rig YAML file of ``cameras`` (what :func:`load_rig` and ``rig.calibration`` read), with an optional
    ``comment`` line on top; returns the path."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    body = yaml.safe_dump({"cameras": [{"name": c.name, **camera_to_sensor_yaml(c)} for c in cameras]},
                          sort_keys=False)
    p.write_text("".join(f"# {line}\n" for line in comment.splitlines()) + body)
    return p


def read_sensor_yaml_file(path: str | Path) -> dict:
    """Read an ASL/Kalibr sensor.yaml (tolerates OpenCV's ``%YAML:1.0`` first line)."""
    p = Path(path)
    if not p.is_file():
        raise CalibrationError(f"{p}: calibration file not found")
    text = p.read_text()
    if text.startswith("%YAML"):
        text = text.split("\n", 1)[1] if "\n" in text else ""
    try:
        return yaml.safe_load(text) or {}
    except yaml.YAMLError as e:
        raise CalibrationError(f"{p}: not valid YAML ({e})") from None


def load_rig(path: str | Path) -> list[CameraCalib]:
    """Cameras of a rig from an EuRoC folder (``mav0/cam*/sensor.yaml``) or a rig YAML file.

    A rig YAML file has ``cameras: [{name: cam0, <sensor.yaml fields>}, ...]``.
    """
    p = Path(path)
    root = p / "mav0" if (p / "mav0").is_dir() else p
    if root.is_dir():
        dirs = sorted((d for d in root.glob("cam*") if (d / "sensor.yaml").is_file()), key=lambda d: int(d.name[3:] or 0))
        if not dirs:
            raise CalibrationError(f"{root}: no cam*/sensor.yaml")
        return [camera_from_sensor_yaml(read_sensor_yaml_file(d / "sensor.yaml"), d.name, str(d / "sensor.yaml"))
                for d in dirs]
    data = read_sensor_yaml_file(p)
    cams = data.get("cameras")
    if not isinstance(cams, list) or not cams:
        raise CalibrationError(f"{p}: expected a non-empty 'cameras' list")
    return [camera_from_sensor_yaml(c, str(c.get("name", f"cam{i}")), f"{p}: cameras[{i}]") for i, c in enumerate(cams)]


@dataclass(frozen=True)
class StereoRectification:
    """A rectified pinhole pair N0/N1 (same K, axes shared, baseline along +x of N0) for two cameras.

    ``R_C0N``/``R_C1N`` rotate rectified rays into each camera; ``T_SN0`` is the rectified left camera in
    the body frame. A point at depth z in N0 has disparity ``u0 - u1 = fx * baseline_m / z``.
    """

    K: np.ndarray
    size: tuple[int, int]
    baseline_m: float
    R_C0N: np.ndarray
    R_C1N: np.ndarray
    T_SN0: np.ndarray
    maps0: tuple[np.ndarray, np.ndarray]
    maps1: tuple[np.ndarray, np.ndarray]

    def rectify(self, img0: np.ndarray, img1: np.ndarray, interpolation: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        import cv2

        interp = cv2.INTER_LINEAR if interpolation is None else interpolation
        return (cv2.remap(img0, *self.maps0, interp, borderMode=cv2.BORDER_CONSTANT),
                cv2.remap(img1, *self.maps1, interp, borderMode=cv2.BORDER_CONSTANT))


def rectified_intrinsics(cam0: CameraCalib, size: tuple[int, int], fov_scale: float = 1.0) -> np.ndarray:
    """Pinhole K [px] of a rectified image of ``size`` = (w, h) from cam0: its horizontal field of view over
    the new width, times ``fov_scale``, principal point at the centre (stereo and monocular depth share it)."""
    w, h = size
    c = cam0.camera
    f = c.fx * (w / c.width) / fov_scale
    return np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])


def stereo_rectification(cam0: CameraCalib, cam1: CameraCalib, size: tuple[int, int],
                         fov_scale: float = 1.0) -> StereoRectification:
    """Rectify cam0/cam1 into pinhole images of ``size`` = (w, h).

    The focal length keeps cam0's horizontal field of view over the new width, times ``fov_scale``
    (< 1 crops to the well-covered centre).
    """
    T_C0C1 = inv_T(cam0.T_SC) @ cam1.T_SC
    b = T_C0C1[:3, 3]
    baseline = float(np.linalg.norm(b))
    if baseline < 1e-6:
        raise CalibrationError(f"{cam0.name}/{cam1.name}: zero baseline, cannot rectify")
    e1 = b / baseline
    z_mean = np.array([0.0, 0.0, 1.0]) + T_C0C1[:3, 2]  # mean optical axis, in C0
    e2 = np.cross(z_mean, e1)
    e2 /= np.linalg.norm(e2)
    e3 = np.cross(e1, e2)
    R_C0N = np.stack([e1, e2, e3], axis=1)
    R_C1N = T_C0C1[:3, :3].T @ R_C0N
    K = rectified_intrinsics(cam0, size, fov_scale)
    T_SN0 = cam0.T_SC.copy()
    T_SN0[:3, :3] = cam0.T_SC[:3, :3] @ R_C0N
    return StereoRectification(K, tuple(size), baseline, R_C0N, R_C1N, T_SN0,
                               cam0.camera.remap_to_pinhole(K, size, R_C0N),
                               cam1.camera.remap_to_pinhole(K, size, R_C1N))
