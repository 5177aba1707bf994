"""The camera view the back end needs: extrinsic, undistortion to normalised coordinates, focal length."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np


@dataclass(frozen=True)
class BackendCamera:
    """What the back end needs of one camera: extrinsic, undistortion to normalised coordinates, focal length."""

    T_SC: np.ndarray
    undistort: Callable[[np.ndarray], np.ndarray]  # (M,2) distorted pixels -> (M,2) normalised (x/z, y/z)
    focal_px: float


def camera_from_calib(calib) -> BackendCamera:
    """From a ``shared.camera.CameraCalib`` (``camera.unproject`` giving rays or normalised points, ``T_SC``)."""
    cam = calib.camera

    def undistort(uv: np.ndarray) -> np.ndarray:
        r = np.asarray(cam.unproject(np.asarray(uv, float)), float)
        return r[:, :2] / r[:, 2:3] if r.shape[1] == 3 else r

    f = float(getattr(cam, "fx", None) or np.asarray(cam.K)[0, 0])
    return BackendCamera(np.asarray(calib.T_SC, float), undistort, f)
