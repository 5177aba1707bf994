"""What the estimator returns per frame (:class:`FrameResult`) and the conversion of gtsam's state covariance to
the order of ``shared.messages.EstimatorState``."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.backend.window.landmarks import WindowLandmarks


@dataclass(frozen=True)
class FrameResult:
    """Causal estimate for one frame, plus the window's keyframe poses after this optimisation."""

    stamp_ns: int
    T_WS: np.ndarray
    v_W: np.ndarray
    gyro_bias: np.ndarray
    acc_bias: np.ndarray
    covariance: np.ndarray  # (15,15), order [rot_S, p_W, v_W, b_g, b_a] as in shared.messages.EstimatorState
    status: str
    keyframe_ids: np.ndarray
    keyframe_stamps_ns: np.ndarray
    keyframe_T_WS: np.ndarray
    num_landmarks: int
    landmarks: WindowLandmarks | None = None  # after a keyframe's optimisation (None for other frames)
    T_SC: np.ndarray | None = None  # (C,4,4) the refined camera extrinsics (backend.refine_extrinsics), else None
    time_offset_s: float = 0.0  # the camera-IMU time offset estimate (backend.estimate_time_offset), else 0


def to_message_covariance(cov_gtsam: np.ndarray, R_WS: np.ndarray) -> np.ndarray:
    """gtsam's [Pose3 (rot_S, t_S), v_W, bias (acc, gyro)] covariance to [rot_S, p_W, v_W, b_g, b_a]."""
    J = np.zeros((15, 15))
    J[0:3, 0:3] = np.eye(3)
    J[3:6, 3:6] = R_WS  # Pose3 translation perturbation is in the body frame
    J[6:9, 6:9] = np.eye(3)
    J[9:12, 12:15] = np.eye(3)
    J[12:15, 9:12] = np.eye(3)
    return J @ cov_gtsam @ J.T
