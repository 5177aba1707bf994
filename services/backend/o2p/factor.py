"""Occupancy-to-point factors (paper eq. 5-7): N depth points of a frame or submap ``a`` should lie on the
L = 0 surface of the occupancy field of a target submap ``b``.

Frames: the points are given in the body frame A of pose ``a`` (``p_A``; callers move camera or submap
points into it by their fixed offsets, e.g. ``T_SC`` or ``T_KM``), the field lives in the submap frame M of
target ``b``, attached by a fixed offset ``T_BM`` to the body frame B of pose ``b``. A point maps as

    q_M = T_MB T_BW T_WA p_A.

Residual and weight: eq. 6 gives ``e_i = L(q_i) / |grad L(q_i)|`` and eq. 7 the weight
``1 / (sigma_map^2 + sigma_d^2)`` with ``sigma_map = |l_min| / (3 |grad L|)``. Their whitened product
simplifies to

    r_i = 3 L / sqrt(l_min^2 + 9 |grad L|^2 sigma_d^2),

which stays bounded where the gradient vanishes. Because ``sigma_map`` depends on the pose through
``grad L``, the Jacobian of ``r_i`` is taken exactly, including the second derivatives of the trilinear
interpolation (its mixed partials; the pure ones are zero), so the analytic Jacobians match finite
differences inside every interpolation cell.

Robustness: the Tukey loss acts on the norm of the whole N-vector (gtsam's Robust noise model reweights a
factor as one block), with the threshold ``tukey_k * sqrt(n)`` for the n points valid when the factor is
built: the factor switches off when the RMS whitened residual exceeds about ``tukey_k``. ``info_scale``
(default 1) scales the information of every point.

Correlated depth errors: eq. 7 treats the N points as independent, but a network's depth errors are
correlated across an image (and across the frames fused into a submap), so N points do not carry N times the
information of one. ``effective_points`` (N_eff > 0) caps a factor at the information of N_eff independent
points: with n points valid when the factor is built, every row is scaled by ``sqrt(min(1, N_eff / n))``
(a constant of the factor, so the Jacobians stay exact). For equicorrelated errors with correlation rho,
the information of n points about a common offset is that of n / (1 + (n - 1) rho) -> 1 / rho independent
ones, so N_eff ~ 1 / rho.

Points outside the target's observed field (any of the 8 interpolation voxels unknown) or in saturated
free space (``|grad L| < grad_min``) give a zero residual row with zero Jacobians: they drop out.

Pose Jacobians use gtsam's Pose3 convention (perturbation ``T Exp(xi)``, ``xi = [omega, v]`` in the body
frame). Either pose can be held fixed (e.g. a submap whose anchor keyframe left the window).
"""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np

from shared.occupancy.query import BlockField

# the 8 corners of a trilinear cell, (dx, dy, dz), x fastest (same order as shared.occupancy.query)
_CORNERS = np.array([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], np.int64)


def trilinear_derivatives(field: BlockField, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Trilinear L (N,), gradient (N, 3) [1/m], mixed second derivatives (N, 3) = (L_xy, L_xz, L_yz) [1/m^2]
    and the validity mask (all 8 voxels observed) at points ``q`` (N, 3) [m] of the field frame. Same
    interpolation as :func:`shared.occupancy.query.interpolate`; invalid rows hold zeros."""
    q = np.asarray(q, np.float64).reshape(-1, 3)
    vs = field.voxel_size
    g = q / vs - 0.5
    i0 = np.floor(g).astype(np.int64)
    f = g - i0
    L8, w8 = field.voxels(i0[:, None, :] + _CORNERS[None])
    valid = (w8 > 0).all(axis=1)
    c = np.where(valid[:, None], L8.astype(np.float64), 0.0)
    cx, cy, cz = (_CORNERS[:, k] for k in range(3))
    w = [np.where(cc, f[:, k:k + 1], 1 - f[:, k:k + 1]) for k, cc in enumerate((cx, cy, cz))]
    s = [np.where(cc, 1.0, -1.0) for cc in (cx, cy, cz)]
    L = np.sum(c * w[0] * w[1] * w[2], axis=1)
    grad = np.stack([np.sum(c * s[0] * w[1] * w[2], axis=1), np.sum(c * w[0] * s[1] * w[2], axis=1),
                     np.sum(c * w[0] * w[1] * s[2], axis=1)], axis=1) / vs
    mixed = np.stack([np.sum(c * s[0] * s[1] * w[2], axis=1), np.sum(c * s[0] * w[1] * s[2], axis=1),
                      np.sum(c * w[0] * s[1] * s[2], axis=1)], axis=1) / vs**2
    return L, grad, mixed, valid


def _hessian_times(mixed: np.ndarray, v: np.ndarray) -> np.ndarray:
    """H v for the trilinear Hessian (zero diagonal, off-diagonals from ``mixed``), row-wise."""
    hxy, hxz, hyz = mixed[:, 0], mixed[:, 1], mixed[:, 2]
    return np.stack([hxy * v[:, 1] + hxz * v[:, 2], hxy * v[:, 0] + hyz * v[:, 2], hxz * v[:, 0] + hyz * v[:, 1]], axis=1)


@dataclasses.dataclass(frozen=True)
class O2PEvaluation:
    r: np.ndarray  # (N,) whitened residuals (0 where dropped)
    J_a: np.ndarray  # (N, 6) d r / d xi_a ([omega, v], body frame)
    J_b: np.ndarray  # (N, 6) d r / d xi_b
    valid: np.ndarray  # (N,) bool: point inside the observed field with |grad L| >= grad_min


class OccupancyToPoint:
    """One occupancy-to-point factor: points ``p_A`` (N, 3) [m] with depth sigmas ``sigma_d`` (N,) [m]
    against the field of a target submap.

    ``key_a`` / ``key_b``: gtsam Pose3 keys of T_WA and T_WB, or None with ``T_WA`` / ``T_WB`` (4x4) fixed.
    ``T_BM``: submap frame in the target's body frame (identity when the submap is anchored at B).
    """

    def __init__(self, field: BlockField, l_min: float, p_A: np.ndarray, sigma_d: np.ndarray, *,
                 key_a: int | None = None, key_b: int | None = None, T_WA: np.ndarray | None = None,
                 T_WB: np.ndarray | None = None, T_BM: np.ndarray | None = None, tukey_k: float = 3.0,
                 grad_min: float = 1.0, info_scale: float = 1.0, effective_points: float = 0.0) -> None:
        p_A = np.asarray(p_A, np.float64).reshape(-1, 3)
        sigma_d = np.broadcast_to(np.asarray(sigma_d, np.float64), (len(p_A),)).copy()
        if len(p_A) == 0:
            raise ValueError("an occupancy-to-point factor needs at least one point")
        if not (np.isfinite(p_A).all() and np.isfinite(sigma_d).all() and (sigma_d >= 0).all()):
            raise ValueError("points and sigmas must be finite, sigmas >= 0")
        if (key_a is None) == (T_WA is None) or (key_b is None) == (T_WB is None):
            raise ValueError("give exactly one of key_a / T_WA and one of key_b / T_WB")
        if key_a is not None and key_a == key_b:
            raise ValueError("points and target share one pose: the factor would be constant")
        if not l_min < 0:
            raise ValueError(f"l_min must be negative, got {l_min}")
        self.field, self.l_min = field, float(l_min)
        self.p_A, self.sigma_d = p_A, sigma_d
        self.key_a, self.key_b = key_a, key_b
        self.T_WA = None if T_WA is None else np.asarray(T_WA, np.float64)
        self.T_WB = None if T_WB is None else np.asarray(T_WB, np.float64)
        self.T_MB = np.linalg.inv(np.eye(4) if T_BM is None else np.asarray(T_BM, np.float64))
        self.tukey_k, self.grad_min = float(tukey_k), float(grad_min)
        if not (info_scale > 0 and effective_points >= 0):
            raise ValueError(f"info_scale > 0 and effective_points >= 0 are required, got {info_scale}, {effective_points}")
        self.info_scale, self.effective_points = float(info_scale), float(effective_points)
        self._sqrt_info = float(np.sqrt(info_scale))  # 1: eq. 7 as it is; the N_eff cap joins in factor()
        self._memo: tuple[bytes, O2PEvaluation] | None = None  # gtsam asks for the error and the Jacobians at one estimate

    @property
    def keys(self) -> list[int]:
        return [k for k in (self.key_a, self.key_b) if k is not None]

    def evaluate(self, T_WA: np.ndarray, T_WB: np.ndarray) -> O2PEvaluation:
        """Whitened residuals and their Jacobians at the given poses (vectorised over the points)."""
        R_WA, t_WA = T_WA[:3, :3], T_WA[:3, 3]
        R_WB, t_WB = T_WB[:3, :3], T_WB[:3, 3]
        R_MB, t_MB = self.T_MB[:3, :3], self.T_MB[:3, 3]
        x_W = self.p_A @ R_WA.T + t_WA
        z_B = (x_W - t_WB) @ R_WB  # R_BW (x_W - t_WB)
        q_M = z_B @ R_MB.T + t_MB
        L, g, mixed, valid = trilinear_derivatives(self.field, q_M)
        g2 = np.einsum("ij,ij->i", g, g)
        valid &= g2 >= self.grad_min**2
        s2 = self.sigma_d**2
        D = np.sqrt(self.l_min**2 + 9.0 * g2 * s2)
        k = self._sqrt_info
        r = np.where(valid, 3.0 * k * L / D, 0.0)
        dr_dq = (3.0 * k / D)[:, None] * g - (27.0 * k * L * s2 / D**3)[:, None] * _hessian_times(mixed, g)
        dr_dq[~valid] = 0.0
        c = dr_dq @ R_MB  # d r / d z_B
        a = c @ R_WB.T @ R_WA  # d r / d (point in A)
        J_a = np.hstack([np.cross(self.p_A, a), a])
        J_b = np.hstack([np.cross(c, z_B), -c])
        return O2PEvaluation(r, J_a, J_b, valid)

    def _poses(self, values: gtsam.Values) -> tuple[np.ndarray, np.ndarray]:
        T_WA = values.atPose3(self.key_a).matrix() if self.key_a is not None else self.T_WA
        T_WB = values.atPose3(self.key_b).matrix() if self.key_b is not None else self.T_WB
        return T_WA, T_WB

    def n_valid(self, values: gtsam.Values | None = None) -> int:
        """Points inside the observed field at ``values`` (or at the fixed poses)."""
        T_WA, T_WB = self._poses(values) if values is not None else (self.T_WA, self.T_WB)
        return int(self.evaluate(T_WA, T_WB).valid.sum())

    def row_scale(self, n_valid: int) -> float:
        """Information scale of every row of a factor built with ``n_valid`` points: info_scale, times
        min(1, N_eff / n_valid) when ``effective_points`` caps the factor."""
        cap = min(1.0, self.effective_points / max(1, n_valid)) if self.effective_points > 0 else 1.0
        return self.info_scale * cap

    def factor(self, n_valid: int | None = None) -> gtsam.CustomFactor:
        """The gtsam factor (N rows, Tukey on the whole vector with threshold tukey_k sqrt(n_valid) in units of
        the unscaled residual); rows scaled by :meth:`row_scale`."""
        n = len(self.p_A)
        self.n_valid_built = n if n_valid is None else int(n_valid)
        self._sqrt_info = float(np.sqrt(self.row_scale(self.n_valid_built)))
        self._memo = None
        c = self.tukey_k * self._sqrt_info * np.sqrt(max(1, self.n_valid_built))
        noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Tukey.Create(c), gtsam.noiseModel.Unit.Create(n))

        def error(this: gtsam.CustomFactor, values: gtsam.Values, H) -> np.ndarray:
            T_WA, T_WB = self._poses(values)
            key = T_WA.tobytes() + T_WB.tobytes()
            if self._memo is not None and self._memo[0] == key:
                ev = self._memo[1]
            else:
                ev = self.evaluate(T_WA, T_WB)
                self._memo = (key, ev)
            if H is not None:
                jac = [j for k, j in ((self.key_a, ev.J_a), (self.key_b, ev.J_b)) if k is not None]
                for i, j in enumerate(jac):
                    H[i] = j
            return ev.r

        return gtsam.CustomFactor(noise, self.keys, error)
