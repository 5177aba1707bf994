"""A camera model whose unprojection is a table lookup (the Newton undistortion costs ~0.1 ms per call and the
frontend calls it dozens of times per frame)."""

from __future__ import annotations

import numpy as np

from shared.camera import CameraModel


class LookupCamera:
    """Duck-types :class:`shared.camera.CameraModel` (project, unproject, undistort_points, size, fx) with
    ``unproject`` interpolated bilinearly from normalised coordinates precomputed at every pixel."""

    def __init__(self, model: CameraModel) -> None:
        self.model = model
        self.width, self.height, self.fx, self.fy = model.width, model.height, model.fx, model.fy
        self.cx, self.cy = model.cx, model.cy
        self.size = model.size
        self._table = model.unproject(model.pixel_grid())[:, :2].reshape(model.height, model.width, 2)

    def project(self, p_C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.model.project(p_C)

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels (N,2) -> rays (N,3) with z = 1; exact model outside the pixel grid."""
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] <= self.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= self.height - 1)
        out = np.empty((len(uv), 3))
        out[:, 2] = 1.0
        if inside.any():
            u, v = uv[inside, 0], uv[inside, 1]
            x0 = np.minimum(np.floor(u).astype(np.int64), self.width - 2)
            y0 = np.minimum(np.floor(v).astype(np.int64), self.height - 2)
            fx, fy = (u - x0)[:, None], (v - y0)[:, None]
            t = self._table
            out[inside, :2] = ((1 - fy) * ((1 - fx) * t[y0, x0] + fx * t[y0, x0 + 1])
                               + fy * ((1 - fx) * t[y0 + 1, x0] + fx * t[y0 + 1, x0 + 1]))
        if (~inside).any():
            out[~inside] = self.model.unproject(uv[~inside])
        return out

    def undistort_points(self, uv: np.ndarray) -> np.ndarray:
        r = self.unproject(uv)
        return np.stack([self.fx * r[:, 0] + self.cx, self.fy * r[:, 1] + self.cy], axis=1)
