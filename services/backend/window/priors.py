"""Prior factors on the oldest state of the estimator's window: at initialisation, after the monocular rebuild
(services/backend/window/mono_init.py) and, as a Gaussian on (pose, velocity, bias), after each marginalisation
(:class:`WindowPrior` keeps them and their covariance); and the window's marginals those Gaussians come from."""

from __future__ import annotations

from typing import Callable

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, L, V, X

from shared.vio.window_rules import state_keys


def state_priors(n: int, T_WS: gtsam.Pose3, v_W: np.ndarray, bias: gtsam.imuBias.ConstantBias,
                 pose_sigmas: np.ndarray, vel_sigma: float, bias_sigmas: np.ndarray) -> list[gtsam.NonlinearFactor]:
    """Independent priors on X(n) (sigmas: rotation [rad] then position [m]), V(n) [m/s] and B(n) (accelerometer
    then gyro)."""
    return [gtsam.PriorFactorPose3(X(n), T_WS, gtsam.noiseModel.Diagonal.Sigmas(pose_sigmas)),
            gtsam.PriorFactorVector(V(n), v_W, gtsam.noiseModel.Isotropic.Sigma(3, vel_sigma)),
            gtsam.PriorFactorConstantBias(B(n), bias, gtsam.noiseModel.Diagonal.Sigmas(bias_sigmas))]


def marginal_prior(values: gtsam.Values, n: int, cov: np.ndarray, extrinsics: tuple[int, ...] = ()
                   ) -> gtsam.NonlinearFactor:
    """The joint marginal ``cov`` of state n's (pose, velocity, bias), order (rotation, position, velocity,
    accelerometer bias, gyro bias), then of the Pose3 variables ``extrinsics`` (keys; online extrinsic refinement,
    services/backend/window/extrinsics.py) in that order, as one Gaussian prior linearised at their estimate in ``values``
    (the correlations kept: the camera poses X(n) E(c) are known better than either factor)."""
    lin = gtsam.Values()
    lin.insert(X(n), values.atPose3(X(n)))
    lin.insert(V(n), values.atVector(V(n)))
    lin.insert(B(n), values.atConstantBias(B(n)))
    for key in extrinsics:
        lin.insert(key, values.atPose3(key))
    info = np.linalg.inv(0.5 * (cov + cov.T))
    info = 0.5 * (info + info.T)
    if not extrinsics:
        R = np.linalg.cholesky(info).T  # R^T R = information
        jf = gtsam.JacobianFactor(X(n), R[:, 0:6], V(n), R[:, 6:9], B(n), R[:, 9:15], np.zeros(15),
                                  gtsam.noiseModel.Unit.Create(15))
        return gtsam.LinearContainerFactor(jf, lin)
    # more keys than a JacobianFactor takes here: the quadratic form 0.5 dx^T info dx as a sum of blocks, summed
    # into one HessianFactor over all keys
    keys = [X(n), V(n), B(n), *extrinsics]
    at = np.cumsum([0, 6, 3, 6] + [6] * len(extrinsics))
    blk = [slice(a, b) for a, b in zip(at[:-1], at[1:])]
    parts = gtsam.GaussianFactorGraph()
    for i, ki in enumerate(keys):
        d = blk[i].stop - blk[i].start
        parts.add(gtsam.HessianFactor(ki, info[blk[i], blk[i]], np.zeros(d), 0.0))
        for j in range(i + 1, len(keys)):
            dj = blk[j].stop - blk[j].start
            parts.add(gtsam.HessianFactor(ki, keys[j], np.zeros((d, d)), info[blk[i], blk[j]], np.zeros(d),
                                          np.zeros((dj, dj)), np.zeros(dj), 0.0))
    return gtsam.LinearContainerFactor(gtsam.HessianFactor(parts), lin)


def window_marginals(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, landmarks,
                     landmark_sigma_m: float) -> tuple[gtsam.Marginals | None, bool]:
    """(marginals of the optimised window or None when gtsam cannot compute them, whether the landmarks had to be
    held). A landmark seen from (nearly) one place only (a body standing still, or turning on the spot) has no
    depth information: LM copes (damping) but the marginals' system is indeterminant. Then weak priors on every
    landmark of ``landmarks`` (ids; ``landmark_sigma_m`` around its estimate) make it determinate; they change the
    states' marginals only where a landmark's position was free anyway."""
    try:
        return gtsam.Marginals(graph, values), False
    except RuntimeError:
        pass
    held = gtsam.NonlinearFactorGraph(graph)
    noise = gtsam.noiseModel.Isotropic.Sigma(3, landmark_sigma_m)
    for lm in landmarks:
        held.add(gtsam.PriorFactorPoint3(L(lm), values.atPoint3(L(lm)), noise))
    try:
        return gtsam.Marginals(held, values), True
    except RuntimeError:
        return None, True


class WindowPrior:
    """The prior on the window's oldest state: its factors (``factors``) and their covariance (``cov``, (15,15),
    :func:`marginal_prior`'s order), set from sigmas by :meth:`reset` or carried to the next state when the oldest
    leaves the window (:meth:`carry`); ``carried`` counts the carries without marginals."""

    def __init__(self) -> None:
        self.factors: list[gtsam.NonlinearFactor] = []
        self.cov = np.eye(15)
        self.carried = 0

    def reset(self, values: gtsam.Values, state: int, pose_sigmas: np.ndarray, vel_sigma: float,
              bias_sigmas: np.ndarray) -> None:
        """Independent priors on ``state`` at its estimate in ``values`` (sigmas as :func:`state_priors`)."""
        self.factors = state_priors(state, values.atPose3(X(state)), values.atVector(V(state)),
                                    values.atConstantBias(B(state)), pose_sigmas, vel_sigma, bias_sigmas)
        self.cov = np.diag(np.r_[pose_sigmas, [vel_sigma] * 3, bias_sigmas] ** 2)

    def carry(self, values: gtsam.Values, new: int, joint_marginal: Callable[[list[int]], np.ndarray | None],
              extrinsics=None, T_SC: np.ndarray | None = None) -> None:
        """The window's marginal of state ``new`` (the next oldest; ``joint_marginal(keys)`` gives the window's
        joint marginal covariance or None) becomes its prior. With online extrinsic refinement (``extrinsics``,
        services/backend/extrinsics.ExtrinsicRefinement, their current estimate ``T_SC`` (C,4,4)) one prior on the
        state and the extrinsics together, each extrinsic's block widened by its walk; without marginals the prior
        keeps the covariance it had (a loose default here would free the window's tilt and position for the rest of
        the run) and the extrinsics keep theirs at ``T_SC``, widened."""
        keys = state_keys(new)
        joint = None if extrinsics is None else joint_marginal([*keys, *extrinsics.keys])
        if joint is not None and np.all(np.isfinite(joint)):
            joint = extrinsics.carry_joint(joint)
            self.cov, self.factors = joint[:15, :15], [marginal_prior(values, new, joint, extrinsics.keys)]
            return
        cov = joint_marginal(keys)
        if cov is None or not np.all(np.isfinite(cov)):
            cov = self.cov
            self.carried += 1
        self.cov, self.factors = cov, [marginal_prior(values, new, cov)]
        if extrinsics is not None:
            extrinsics.carry_apart(T_SC)
