"""The camera view the VIO core needs (the keyframe window and the fast path): extrinsic, undistortion to
normalised coordinates, focal length; built from the rig's calibrations by :func:`rig_cameras`."""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from shared.lookup_camera import LookupCamera


@dataclasses.dataclass(frozen=True)
class VioCamera:
    """What the VIO core needs of one camera: extrinsic, undistortion to normalised coordinates, focal length."""

    T_SC: np.ndarray
    undistort: Callable[[np.ndarray], np.ndarray]  # (M,2) distorted pixels -> (M,2) normalised (x/z, y/z)
    focal_px: float


def camera_from_calib(calib) -> VioCamera:
    """From a ``shared.camera.CameraCalib`` (``camera.unproject`` giving rays or normalised points, ``T_SC``)."""
    cam = calib.camera

    def undistort(uv: np.ndarray) -> np.ndarray:
        r = np.asarray(cam.unproject(np.asarray(uv, float)), float)
        return r[:, :2] / r[:, 2:3] if r.shape[1] == 3 else r

    f = float(getattr(cam, "fx", None) or np.asarray(cam.K)[0, 0])
    return VioCamera(np.asarray(calib.T_SC, float), undistort, f)


def rig_cameras(cameras) -> list[VioCamera]:
    """The rig's cameras (``shared.rig`` calibrations) as the VIO core uses them: undistortion by table lookup (the
    exact Newton inverse costs ~10 ms per frame at 300 observations)."""
    return [camera_from_calib(dataclasses.replace(c, camera=LookupCamera(c.camera))) for c in cameras]
