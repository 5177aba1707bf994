"""Estimator states as the two processes publish them: the placeholder of a frame without a pose, and a state
moved into the frame W' the loop closer publishes in."""

from __future__ import annotations

import numpy as np

from shared.messages import EstimatorState, Header


def placeholder_state(header: Header, status: str) -> EstimatorState:
    """A frame's answer when there is no pose for it (``status`` 'initialising' or 'reset'): identity pose, zero
    velocity and biases, NaN covariance. Lockstep players wait for an answer to every frame."""
    return EstimatorState(header=header, T_WS=np.eye(4), v_W=np.zeros(3), gyro_bias=np.zeros(3), acc_bias=np.zeros(3),
                          covariance=np.full((15, 15), np.nan), status=status)


def corrected_state(msg: EstimatorState, T: np.ndarray) -> EstimatorState:
    """``msg`` moved by the rigid correction T (= T_W'W): pose, velocity and the covariance's p/v blocks."""
    R = T[:3, :3]
    J = np.eye(15)
    J[3:6, 3:6] = J[6:9, 6:9] = R
    return EstimatorState(header=msg.header, T_WS=T @ msg.T_WS, v_W=R @ msg.v_W, gyro_bias=msg.gyro_bias,
                          acc_bias=msg.acc_bias, covariance=J @ msg.covariance @ J.T, status=msg.status)
