"""Reprojection factors of the rig's cameras, as both the window estimator and the per-frame fast path build them.

Observations (distorted pixels) are undistorted by the camera model to normalised coordinates and enter
``GenericProjectionFactorCal3_S2`` with an identity calibration and ``body_P_sensor = T_SC_i``, noise
sigma_px / f_i, wrapped in a Cauchy robust model (k in units of sigma). With an exposure time, an observation
made while the rig turns has that sigma scaled by :meth:`ProjectionModel.blur_scale`: its motion blur (a streak of
|omega_xy| x exposure x f pixels, spread length / sqrt(12)) added in quadrature.
"""

from __future__ import annotations

import gtsam
import gtsam_unstable
import numpy as np

from services.backend.cameras import BackendCamera
from services.backend.motion_only import FixedPoints


class ProjectionModel:
    """Factor maker for one rig: ``factor(xy, camera, pose_key, landmark_key)``."""

    def __init__(self, cameras: list[BackendCamera], sigma_px: float, cauchy_k: float,
                 exposure_time_s: float = 0.0) -> None:
        if not exposure_time_s >= 0:
            raise ValueError(f"exposure_time_s must be >= 0 s, got {exposure_time_s}")
        self.cameras = list(cameras)
        self.sigma_px, self.cauchy_k = float(sigma_px), float(cauchy_k)
        self.exposure_time_s = float(exposure_time_s)
        self._T_SC = np.array([c.T_SC for c in self.cameras], float)
        self._cal = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)
        self._body_P_cam = [gtsam.Pose3(c.T_SC) for c in self.cameras]
        self._noise = [self._noise_model(c, 1.0) for c in range(len(self.cameras))]

    def _noise_model(self, camera: int, scale: float):
        return gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Cauchy.Create(self.cauchy_k),
            gtsam.noiseModel.Isotropic.Sigma(2, scale * self.sigma_px / self.cameras[camera].focal_px))

    def _noise_for(self, camera: int, scale: float):
        return self._noise[camera] if scale == 1.0 else self._noise_model(camera, scale)

    def blur_scale(self, omega_S: np.ndarray) -> np.ndarray:
        """(C,) factor on each camera's sigma for a frame taken while the rig turns at ``omega_S`` (3,) [rad/s,
        body frame, bias removed]: sqrt(1 + (b / sqrt(12) / sigma_px)^2) with b = |omega_xy in the camera| x
        exposure x focal length [px], the length of the blur streak at the image centre; ones with no exposure
        time."""
        if self.exposure_time_s <= 0:
            return np.ones(len(self.cameras))
        w_C = np.einsum("cji,j->ci", self._T_SC[:, :3, :3], np.asarray(omega_S, float).reshape(3))  # R_SC^T omega
        focal = np.array([c.focal_px for c in self.cameras], float)
        streak_px = np.hypot(w_C[:, 0], w_C[:, 1]) * self.exposure_time_s * focal
        return np.sqrt(1.0 + (streak_px / np.sqrt(12.0) / self.sigma_px) ** 2)

    def factor(self, xy: np.ndarray, camera: int, pose_key: int, landmark_key: int,
               scale: float = 1.0) -> gtsam.NonlinearFactor:
        """Reprojection factor of normalised coordinates ``xy`` (2,) seen by ``camera`` from pose ``pose_key``; its
        sigma times ``scale`` (:meth:`blur_scale`)."""
        return gtsam.GenericProjectionFactorCal3_S2(xy, self._noise_for(camera, scale), pose_key, landmark_key,
                                                    self._cal, False, False, self._body_P_cam[camera])

    def factor_with_extrinsic(self, xy: np.ndarray, camera: int, pose_key: int, extrinsic_key: int,
                              landmark_key: int, scale: float = 1.0) -> gtsam.NonlinearFactor:
        """The same factor with the camera's extrinsic T_SC a variable (``extrinsic_key``, a Pose3) instead of fixed:
        online extrinsic refinement (services/backend/extrinsics.py)."""
        return gtsam_unstable.ProjectionFactorPPPCal3_S2(xy, self._noise_for(camera, scale), pose_key, extrinsic_key,
                                                         landmark_key, self._cal, False, False)

    def set_extrinsics(self, T_SC: np.ndarray) -> None:
        """Use ``T_SC`` (C,4,4) from now on (refined extrinsics): in new fixed-extrinsic factors and fixed points."""
        T_SC = np.asarray(T_SC, float)
        if T_SC.shape != self._T_SC.shape:
            raise ValueError(f"extrinsics of shape {T_SC.shape} for a rig of {len(self.cameras)} cameras")
        self._T_SC = T_SC.copy()
        self._body_P_cam = [gtsam.Pose3(T) for T in self._T_SC]

    @property
    def T_SC(self) -> np.ndarray:
        """(C,4,4) the extrinsics in use (a copy)."""
        return self._T_SC.copy()

    def fixed_points(self, p_W: np.ndarray, xy: np.ndarray, camera: np.ndarray,
                     scale: np.ndarray | None = None) -> FixedPoints:
        """The same reprojection terms for landmarks held fixed at ``p_W`` (M,3), observed at normalised ``xy``
        (M,2) by ``camera`` (M,): what a motion-only solve (services/backend/motion_only.py) takes; each camera's
        sigma times ``scale`` (C,) (:meth:`blur_scale`; None: 1)."""
        sigma = np.array([self.sigma_px / c.focal_px for c in self.cameras])
        if scale is not None:
            sigma = sigma * np.asarray(scale, float)
        return FixedPoints(np.asarray(p_W, float).reshape(-1, 3), np.asarray(xy, float).reshape(-1, 2),
                           np.asarray(camera, np.int64).reshape(-1), self._T_SC, sigma, self.cauchy_k)

    def undistort(self, camera_index: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """(M,2) normalised coordinates of distorted pixels ``uv`` (M,2), each by its camera."""
        xy = np.empty((len(uv), 2))
        for c in np.unique(camera_index):
            m = camera_index == c
            xy[m] = self.cameras[c].undistort(uv[m])
        return xy
