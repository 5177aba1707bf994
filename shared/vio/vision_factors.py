"""Reprojection factors of the rig's cameras, as both the window estimator and the per-frame fast path build them.

Observations (distorted pixels) are undistorted by the camera model to normalised coordinates and enter
``GenericProjectionFactorCal3_S2`` with an identity calibration and ``body_P_sensor = T_SC_i``, noise
sigma_px / f_i, wrapped in a Cauchy robust model (k in units of sigma).
"""

from __future__ import annotations

import gtsam
import gtsam_unstable
import numpy as np

from shared.vio.cameras import VioCamera
from shared.vio.motion_only import FixedPoints


class ProjectionModel:
    """Factor maker for one rig: ``factor(xy, camera, pose_key, landmark_key)``."""

    def __init__(self, cameras: list[VioCamera], sigma_px: float, cauchy_k: float) -> None:
        self.cameras = list(cameras)
        self.sigma_px, self.cauchy_k = float(sigma_px), float(cauchy_k)
        self._T_SC = np.array([c.T_SC for c in self.cameras], float)
        self._cal = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)
        self._body_P_cam = [gtsam.Pose3(c.T_SC) for c in self.cameras]
        self._noise = [gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(cauchy_k),
                                                      gtsam.noiseModel.Isotropic.Sigma(2, sigma_px / c.focal_px))
                       for c in self.cameras]

    def factor(self, xy: np.ndarray, camera: int, pose_key: int, landmark_key: int) -> gtsam.NonlinearFactor:
        """Reprojection factor of normalised coordinates ``xy`` (2,) seen by ``camera`` from pose ``pose_key``."""
        return gtsam.GenericProjectionFactorCal3_S2(xy, self._noise[camera], pose_key, landmark_key, self._cal,
                                                    False, False, self._body_P_cam[camera])

    def factor_with_extrinsic(self, xy: np.ndarray, camera: int, pose_key: int, extrinsic_key: int,
                              landmark_key: int) -> gtsam.NonlinearFactor:
        """The same factor with the camera's extrinsic T_SC a variable (``extrinsic_key``, a Pose3) instead of fixed:
        online extrinsic refinement (services/backend/window/extrinsics.py)."""
        return gtsam_unstable.ProjectionFactorPPPCal3_S2(xy, self._noise[camera], pose_key, extrinsic_key, landmark_key,
                                                         self._cal, False, False)

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

    def fixed_points(self, p_W: np.ndarray, xy: np.ndarray, camera: np.ndarray) -> FixedPoints:
        """The same reprojection terms for landmarks held fixed at ``p_W`` (M,3), observed at normalised ``xy``
        (M,2) by ``camera`` (M,): what a motion-only solve (shared/vio/motion_only.py) takes."""
        sigma = np.array([self.sigma_px / c.focal_px for c in self.cameras])
        return FixedPoints(np.asarray(p_W, float).reshape(-1, 3), np.asarray(xy, float).reshape(-1, 2),
                           np.asarray(camera, np.int64).reshape(-1), self._T_SC, sigma, self.cauchy_k)

    def undistort(self, camera_index: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """(M,2) normalised coordinates of distorted pixels ``uv`` (M,2), each by its camera."""
        xy = np.empty((len(uv), 2))
        for c in np.unique(camera_index):
            m = camera_index == c
            xy[m] = self.cameras[c].undistort(uv[m])
        return xy
