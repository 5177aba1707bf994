"""Absolute trajectory error (ATE) after alignment, as in the paper's sec. V.

Alignment modes (the estimate is mapped onto the ground truth, ``p_gt ~ s R p_est + t``):
``se3`` (Umeyama without scale, the default and the paper's), ``sim3`` (with scale), ``posyaw``
(translation and rotation about gravity only: the 4 unobservable DoF of VIO) and ``none``.
``align_first_s`` aligns on the first seconds only and evaluates on everything (drift-revealing).
"""

from __future__ import annotations

import dataclasses

import numpy as np

MODES = ("se3", "sim3", "posyaw", "none")


@dataclasses.dataclass(frozen=True)
class Alignment:
    R: np.ndarray  # (3,3) rotation applied to the estimate
    t: np.ndarray  # (3,) translation [m]
    scale: float

    def apply(self, p: np.ndarray) -> np.ndarray:
        return self.scale * p @ self.R.T + self.t

    def matrix(self) -> np.ndarray:
        """4x4 homogeneous form (scale folded into the rotation block): ground-truth frame <- estimate frame."""
        T = np.eye(4)
        T[:3, :3] = self.scale * self.R
        T[:3, 3] = self.t
        return T


@dataclasses.dataclass(frozen=True)
class AteResult:
    rmse_m: float
    mean_m: float
    median_m: float
    max_m: float
    matched: int
    alignment: Alignment
    errors_m: np.ndarray  # (N,) per matched pose [m]
    stamps_ns: np.ndarray  # (N,) matched times [ns]


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool) -> Alignment:
    """Least-squares similarity (or rigid) transform with ``dst ~ s R src + t`` (Umeyama 1991)."""
    src = np.asarray(src, float)
    dst = np.asarray(dst, float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"umeyama needs two (N,3) arrays of equal shape, got {src.shape} and {dst.shape}")
    if len(src) < 3:
        raise ValueError(f"alignment needs at least 3 matched positions, got {len(src)}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    var_s = (xs ** 2).sum() / len(src)
    scale = float(np.trace(np.diag(D) @ S) / var_s) if with_scale and var_s > 0 else 1.0
    return Alignment(R, mu_d - scale * R @ mu_s, scale)


def align_posyaw(src: np.ndarray, dst: np.ndarray) -> Alignment:
    """Rigid alignment restricted to a rotation about z (gravity) and a translation."""
    src = np.asarray(src, float)
    dst = np.asarray(dst, float)
    if len(src) < 2:
        raise ValueError(f"position+yaw alignment needs at least 2 matched positions, got {len(src)}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    # maximise sum over points of dst_xy . Rz(yaw) src_xy
    a = (xs[:, 0] * xd[:, 0] + xs[:, 1] * xd[:, 1]).sum()
    b = (xs[:, 0] * xd[:, 1] - xs[:, 1] * xd[:, 0]).sum()
    yaw = np.arctan2(b, a)
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return Alignment(R, mu_d - R @ mu_s, 1.0)


def associate(stamps_a_ns: np.ndarray, stamps_b_ns: np.ndarray, max_diff_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices (ia, ib) pairing each time of ``a`` with the nearest time of ``b`` within ``max_diff_ns``."""
    a = np.asarray(stamps_a_ns, np.int64)
    b = np.asarray(stamps_b_ns, np.int64)
    if len(b) == 0 or len(a) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    order = np.argsort(b, kind="stable")
    bs = b[order]
    j = np.clip(np.searchsorted(bs, a), 1, len(bs) - 1) if len(bs) > 1 else np.zeros(len(a), int)
    left = bs[np.maximum(j - 1, 0)]
    right = bs[j]
    pick = np.where(np.abs(a - left) <= np.abs(right - a), np.maximum(j - 1, 0), j)
    diff = np.abs(bs[pick] - a)
    ok = diff <= max_diff_ns
    return np.nonzero(ok)[0], order[pick[ok]]


def compute_ate(gt_stamps_ns: np.ndarray, gt_p: np.ndarray, est_stamps_ns: np.ndarray, est_p: np.ndarray,
                mode: str = "se3", align_first_s: float | None = None, max_diff_ns: int = 10_000_000) -> AteResult:
    """ATE of estimated positions ``est_p`` (N,3) against ground truth ``gt_p`` (M,3), both in metres."""
    if mode not in MODES:
        raise ValueError(f"unknown alignment mode {mode!r}; choose one of {MODES}")
    ie, ig = associate(est_stamps_ns, gt_stamps_ns, max_diff_ns)
    if len(ie) < 3:
        raise ValueError(f"only {len(ie)} estimated poses have ground truth within {max_diff_ns / 1e6:.1f} ms")
    stamps = np.asarray(est_stamps_ns, np.int64)[ie]
    p_est = np.asarray(est_p, float)[ie]
    p_gt = np.asarray(gt_p, float)[ig]
    fit = np.ones(len(ie), bool)
    if align_first_s is not None:
        fit = stamps - stamps[0] <= int(align_first_s * 1e9)
    if mode == "none":
        al = Alignment(np.eye(3), np.zeros(3), 1.0)
    elif mode == "posyaw":
        al = align_posyaw(p_est[fit], p_gt[fit])
    else:
        al = umeyama(p_est[fit], p_gt[fit], with_scale=(mode == "sim3"))
    err = np.linalg.norm(al.apply(p_est) - p_gt, axis=1)
    return AteResult(float(np.sqrt(np.mean(err ** 2))), float(err.mean()), float(np.median(err)), float(err.max()),
                     len(err), al, err, stamps)


def run_alignment(est_path, gt_path, mode: str = "se3") -> np.ndarray:
    """4x4 transform taking a run's world frame into the ground truth's, from the run's trajectory file
    (TUM or EuRoC CSV) aligned to the ground truth: what puts the run's map next to the ground-truth mesh."""
    from shared.euroc import read_trajectory

    est, gt = read_trajectory(est_path), read_trajectory(gt_path)
    return compute_ate(gt.stamps_ns, gt.p_WS, est.stamps_ns, est.p_WS, mode=mode).alignment.matrix()
