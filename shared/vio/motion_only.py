"""Motion-only update of the newest state with the rest of the window held fixed.

Between keyframes the newest (non-keyframe) state is the only unknown worth solving for: it leaves the
window after the frame. Its pose, velocity and bias (15 unknowns) are solved against the IMU factor from the
last keyframe (and any other gtsam factor on it, e.g. a standing-still factor) and the reprojections of
landmarks held fixed at the window's estimate.

The solve is a small Gauss-Newton in numpy rather than a gtsam graph: the gtsam factors touching the state are
linearised by gtsam (the keyframe's variables count as constants), the reprojections of the fixed points are
linearised in one vectorised pass (pose-only Jacobians, Cauchy weights as in ``vision_factors``), the 15x15
normal equations are solved and the step is applied with gtsam's own retractions; a step that raises the
robust cost is halved. Same cost and minimum as the window's factors would give with landmarks and keyframe
pinned, at a fraction of the time (no landmark variables to eliminate).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X

from shared.geometry import skew

MIN_DEPTH_M = 1e-3  # points closer than this to a camera (or behind it) give no constraint
_DIMS = {ord("x"): 6, ord("v"): 3, ord("b"): 6, ord("l"): 3}


@dataclass(frozen=True)
class FixedPoints:
    """Observations of landmarks whose positions are held fixed: the reprojection terms of a motion-only solve."""

    p_W: np.ndarray  # (M,3) landmark positions [m]
    xy: np.ndarray  # (M,2) observed normalised image coordinates
    camera: np.ndarray  # (M,) camera index
    T_SC: np.ndarray  # (C,4,4) camera extrinsics
    sigma: np.ndarray  # (C,) observation sigma in normalised coordinates (sigma_px / focal_px)
    cauchy_k: float  # Cauchy scale, in units of sigma

    def __len__(self) -> int:
        return len(self.p_W)


def _residuals(T_WS: np.ndarray, pts: FixedPoints, jacobians: bool):
    """Whitened residuals (M,2), the mask of points in front, and (with ``jacobians``) d residual / d pose (M,2,6)
    for a right perturbation T_WS Exp([omega, v]) (gtsam's Pose3 tangent order)."""
    R, t = T_WS[:3, :3], T_WS[:3, 3]
    R_SC, t_SC = pts.T_SC[pts.camera, :3, :3], pts.T_SC[pts.camera, :3, 3]
    p_S = (pts.p_W - t) @ R
    p_C = np.einsum("mji,mj->mi", R_SC, p_S - t_SC)
    z = p_C[:, 2]
    front = z > MIN_DEPTH_M
    zs = np.where(front, z, 1.0)
    s = pts.sigma[pts.camera][:, None]
    e = np.where(front[:, None], (p_C[:, :2] / zs[:, None] - pts.xy) / s, 0.0)
    if not jacobians:
        return e, front, None
    J_pi = np.zeros((len(z), 2, 3))
    J_pi[:, 0, 0] = J_pi[:, 1, 1] = 1.0 / zs
    J_pi[:, :, 2] = -p_C[:, :2] / zs[:, None] ** 2
    R_CS = np.transpose(R_SC, (0, 2, 1))
    d_pC = np.concatenate([R_CS @ skew(p_S), -R_CS], axis=2)  # (M,3,6): d p_C / d [omega, v]
    J = J_pi @ d_pC / s[:, :, None]
    return e, front, np.where(front[:, None, None], J, 0.0)


def _robust_cost(e: np.ndarray, k: float) -> float:
    return float(np.sum(0.5 * k * k * np.log1p(np.sum(e * e, axis=1) / (k * k))))


def _cost(values: gtsam.Values, n: int, factors, pts: FixedPoints | None) -> float:
    c = sum(f.error(values) for f in factors)
    if pts is not None and len(pts):
        c += _robust_cost(_residuals(values.atPose3(X(n)).matrix(), pts, False)[0], pts.cauchy_k)
    return c


def _columns(keys, wanted: dict[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Columns of a factor's Jacobian (its variables ``keys``, in order) that belong to the ``wanted`` keys
    (key -> offset in the unknowns) and where they go."""
    src, dst, col = [], [], 0
    for key in keys:
        d = _DIMS[gtsam.Symbol(key).chr()]
        if key in wanted:
            src += range(col, col + d)
            dst += range(wanted[key], wanted[key] + d)
        col += d
    return np.array(src, int), np.array(dst, int)


def _subset(values: gtsam.Values, keys) -> gtsam.Values:
    """The values of ``keys`` alone (the solve copies its values at every trial step: not the whole window)."""
    out = gtsam.Values()
    for key in keys:
        c = gtsam.Symbol(key).chr()
        out.insert(key, values.atPose3(key) if c == ord("x") else values.atConstantBias(key) if c == ord("b")
                   else np.asarray(values.atVector(key)) if c == ord("v") else values.atPoint3(key))
    return out


def _retract(values: gtsam.Values, key: int, delta: np.ndarray) -> None:
    """Apply the step ``delta`` to ``key`` in place, with gtsam's own retraction for its type."""
    c = gtsam.Symbol(key).chr()
    if c == ord("x"):
        values.update(key, values.atPose3(key).retract(delta))
    elif c == ord("b"):
        values.update(key, values.atConstantBias(key).retract(delta))
    else:
        values.update(key, np.asarray(values.atVector(key)) + delta)


def optimise_latest(values: gtsam.Values, n: int, factors: list[gtsam.NonlinearFactor], points: FixedPoints | None,
                    iterations: int, step_tol: float = 1e-8, also: tuple[int, ...] = (),
                    relative_tol: float = 0.0) -> gtsam.Values:
    """Optimise X(n), V(n), B(n) against ``factors`` (gtsam factors; their other variables are held at ``values``)
    and the fixed ``points``; returns the updated values of those three keys only. ``also``: further velocity or
    bias keys solved with them (e.g. the anchor keyframe's, held by a prior among ``factors`` instead of pinned).
    Stops after ``iterations``, or once a step is shorter than ``step_tol`` or lowers the cost by less than
    ``relative_tol`` of it (as gtsam's LM does with its relative error tolerance).
    Raises RuntimeError when the normal equations are singular (nothing constrains the state)."""
    wanted = {X(n): 0, V(n): 6, B(n): 9}
    dim = 15
    for key in also:
        wanted[key] = dim
        dim += _DIMS[gtsam.Symbol(key).chr()]
    cur = _subset(values, {k for f in factors for k in f.keys()} | set(wanted))
    cost = _cost(cur, n, factors, points)
    columns = [_columns(f.keys(), wanted) for f in factors]
    for _ in range(max(1, iterations)):
        H, g = np.zeros((dim, dim)), np.zeros(dim)
        for f, (src, dst) in zip(factors, columns):
            A, b = f.linearize(cur).jacobian()
            A_n = np.zeros((A.shape[0], dim))
            A_n[:, dst] = A[:, src]
            H += A_n.T @ A_n
            g += A_n.T @ b
        if points is not None and len(points):
            e, _, J = _residuals(cur.atPose3(X(n)).matrix(), points, True)
            k2 = points.cauchy_k ** 2
            w = k2 / (k2 + np.sum(e * e, axis=1))  # Cauchy weights (iteratively reweighted least squares)
            H[:6, :6] += np.einsum("m,mai,maj->ij", w, J, J)
            g[:6] -= np.einsum("m,mai,ma->i", w, J, e)
        try:
            delta = np.linalg.solve(H, g)
        except np.linalg.LinAlgError as exc:
            raise RuntimeError(f"motion-only solve: {exc}") from None
        if not np.all(np.isfinite(delta)):
            raise RuntimeError("motion-only solve: no finite step")
        for _half in range(6):  # a step that raises the cost is halved
            trial = gtsam.Values(cur)
            for key, at in wanted.items():
                _retract(trial, key, delta[at:at + _DIMS[gtsam.Symbol(key).chr()]])
            c = _cost(trial, n, factors, points)
            if c <= cost:
                break
            delta = 0.5 * delta
        else:
            break
        converged = cost - c <= relative_tol * cost or np.linalg.norm(delta) < step_tol
        cur, cost = trial, c
        if converged:
            break
    out = gtsam.Values()
    out.insert(X(n), cur.atPose3(X(n)))
    out.insert(V(n), np.asarray(cur.atVector(V(n))))
    out.insert(B(n), cur.atConstantBias(B(n)))
    return out
