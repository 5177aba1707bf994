"""Motion-only update of the newest state with the rest of the window held fixed.

Between keyframes the newest (non-keyframe) state is the only unknown worth solving for: it leaves the
window after the frame. Its pose, velocity and bias are optimised against the IMU factor from the last
keyframe and its reprojection factors, with the keyframe state and the landmarks pinned by tight priors at
their current estimates (a few hundred factors instead of the window's thousands).
"""

from __future__ import annotations

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, L, V, X

PIN_SIGMA = 1e-6  # prior sigma pinning the fixed variables (rad, m, m/s, bias units)


def optimise_latest(values: gtsam.Values, k: int, n: int, imu_factor: gtsam.NonlinearFactor,
                    projections: list[gtsam.NonlinearFactor], landmarks: list[int], iterations: int
                    ) -> gtsam.Values:
    """Optimise X(n), V(n), B(n); returns the updated values of those three keys only."""
    g = gtsam.NonlinearFactorGraph()
    v = gtsam.Values()
    g.add(gtsam.PriorFactorPose3(X(k), values.atPose3(X(k)), gtsam.noiseModel.Isotropic.Sigma(6, PIN_SIGMA)))
    g.add(gtsam.PriorFactorVector(V(k), values.atVector(V(k)), gtsam.noiseModel.Isotropic.Sigma(3, PIN_SIGMA)))
    g.add(gtsam.PriorFactorConstantBias(B(k), values.atConstantBias(B(k)),
                                        gtsam.noiseModel.Isotropic.Sigma(6, PIN_SIGMA)))
    g.add(imu_factor)
    pin3 = gtsam.noiseModel.Isotropic.Sigma(3, PIN_SIGMA)
    for lm in landmarks:
        p = values.atPoint3(L(lm))
        g.add(gtsam.PriorFactorPoint3(L(lm), p, pin3))
        v.insert(L(lm), p)
    for f in projections:
        g.add(f)
    for key in (X(k), V(k), B(k), X(n), V(n), B(n)):
        v.insert(key, values.atPose3(key) if key in (X(k), X(n)) else
                 values.atVector(key) if key in (V(k), V(n)) else values.atConstantBias(key))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(iterations)
    order = gtsam.Ordering()
    for lm in landmarks:
        order.push_back(L(lm))
    for key in (X(k), V(k), B(k), X(n), V(n), B(n)):
        order.push_back(key)
    params.setOrdering(order)
    res = gtsam.LevenbergMarquardtOptimizer(g, v, params).optimize()
    out = gtsam.Values()
    out.insert(X(n), res.atPose3(X(n)))
    out.insert(V(n), np.asarray(res.atVector(V(n))))
    out.insert(B(n), res.atConstantBias(B(n)))
    return out
