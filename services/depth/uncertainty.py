"""Depth uncertainty arithmetic of the paper (numpy, per pixel, NaN = invalid).

- eq. 11: disparity u [px] with sigma_u -> depth f b / u with sigma f b sigma_u / u^2;
- eq. 13: log depth with sigma_log -> depth exp(log d) with sigma d sigma_log;
- eq. 14: inverse-variance fusion of two independent estimates;
- heuristic sigma models (supereight2 style): linear and quadratic in depth;
- sec. V-A calibration: one gain k so that the mean Mahalanobis distance |d - d_gt| / (k sigma) is 1, or (rule
  'median', robust to the gross outliers of a synthetic validation set) its median is ln 2, the Laplacian's;
- metrics: AbsRel, RMSE, delta < 1.25, mean Mahalanobis, Laplacian/Gaussian NLL, fraction within n sigma.
"""
from __future__ import annotations

import numpy as np


def disparity_to_depth(u: np.ndarray, sigma_u: np.ndarray, f_px: float, baseline_m: float,
                       min_disparity: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 11. Pixels with u < min_disparity [px] or non-finite values become NaN."""
    u = np.asarray(u, np.float64)
    ok = np.isfinite(u) & np.isfinite(sigma_u) & (u >= min_disparity)
    us = np.where(ok, u, 1.0)
    fb = f_px * baseline_m
    depth = np.where(ok, fb / us, np.nan)
    sigma = np.where(ok, fb / (us * us) * sigma_u, np.nan)
    return depth.astype(np.float32), sigma.astype(np.float32)


def logdepth_to_depth(log_d: np.ndarray, sigma_log: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 13."""
    d = np.exp(np.asarray(log_d, np.float64))
    return d.astype(np.float32), (d * sigma_log).astype(np.float32)


def heuristic_sigma(depth: np.ndarray, model: str, coeff: float) -> np.ndarray:
    """Heuristic depth sigma [m]: 'quadratic' coeff * d^2 (constant disparity sigma: coeff = sigma_u / (f b)),
    'linear' coeff * d."""
    d = np.asarray(depth, np.float64)
    if model == "quadratic":
        return (coeff * d * d).astype(np.float32)
    if model == "linear":
        return (coeff * d).astype(np.float32)
    raise ValueError(f"unknown heuristic sigma model {model!r} (linear, quadratic)")


def fuse(d1: np.ndarray, s1: np.ndarray, d2: np.ndarray, s2: np.ndarray,
         rho: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 14 per pixel, generalised to errors with correlation ``rho`` (0: eq. 14, independent errors): the
    best linear combination of the two depths, its weights clipped to [0, 1] (a strongly correlated, much worse
    source is left out rather than subtracted), and the sigma of that combination. A pixel valid in one source only
    (finite depth, finite sigma > 0) keeps that source; invalid in both gives NaN."""
    if not 0.0 <= rho < 1.0:
        raise ValueError(f"fusion correlation {rho} outside [0, 1)")
    d1, s1, d2, s2 = (np.asarray(a, np.float64) for a in (d1, s1, d2, s2))
    ok1 = np.isfinite(d1) & np.isfinite(s1) & (s1 > 0)
    ok2 = np.isfinite(d2) & np.isfinite(s2) & (s2 > 0)
    a = np.where(ok1, s1, 1.0)
    b = np.where(ok2, s2, 1.0)
    cov = rho * a * b
    w1 = np.clip((b * b - cov) / (a * a + b * b - 2 * cov), 0.0, 1.0)
    w1 = np.where(ok1 & ok2, w1, ok1.astype(np.float64))  # one valid source: it alone
    w2 = 1.0 - w1
    any_ok = ok1 | ok2
    var = np.where(any_ok, w1 * w1 * a * a + w2 * w2 * b * b + 2 * w1 * w2 * cov, np.nan)
    depth = np.where(any_ok, w1 * np.where(ok1, d1, 0.0) + w2 * np.where(ok2, d2, 0.0), np.nan)
    return depth.astype(np.float32), np.sqrt(var).astype(np.float32)


def _valid(est, sigma, gt):
    est, sigma, gt = (np.asarray(a, np.float64).ravel() for a in (est, sigma, gt))
    ok = np.isfinite(est) & np.isfinite(sigma) & (sigma > 0) & np.isfinite(gt) & (gt > 0)
    return est[ok], sigma[ok], gt[ok]


GAIN_RULES = ("mean", "median")


def gain_from_ratios(ratios: np.ndarray, rule: str = "mean") -> float:
    """The gain k for |error| / sigma ratios: 'mean' (sec. V-A) mean(ratio / k) = 1; 'median' median(ratio / k) = ln 2,
    the Laplacian's median, so that a tail of gross errors does not inflate every pixel's sigma."""
    r = np.asarray(ratios, np.float64).ravel()
    r = r[np.isfinite(r)]
    if r.size == 0:
        raise ValueError("calibration gain: no valid pixels")
    if rule == "mean":
        return float(np.mean(r))
    if rule == "median":
        return float(np.median(r) / np.log(2.0))
    raise ValueError(f"unknown gain rule {rule!r} ({', '.join(GAIN_RULES)})")


def calibration_gain(est: np.ndarray, sigma: np.ndarray, gt: np.ndarray, rule: str = "mean") -> float:
    """Sec. V-A: the gain k with mean(|est - gt| / (k sigma)) = 1 over valid pixels (or its ``rule``)."""
    e, s, g = _valid(est, sigma, gt)
    return gain_from_ratios(np.abs(e - g) / s, rule)


def depth_metrics(est: np.ndarray, sigma: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """Accuracy and uncertainty metrics over pixels valid in all three maps."""
    e, s, g = _valid(est, sigma, gt)
    if e.size == 0:
        return {"n": 0}
    err = e - g
    z = np.abs(err) / s
    ratio = np.maximum(e / g, g / e)
    return {
        "n": int(e.size),
        "absrel": float(np.mean(np.abs(err) / g)),
        "rmse": float(np.sqrt(np.mean(err ** 2))),
        "delta1": float(np.mean(ratio < 1.25)),
        "mahalanobis": float(np.mean(z)),
        "nll_laplace": float(np.mean(z + np.log(2 * s))),  # sigma as the Laplacian scale (eq. 9)
        "nll_gauss": float(np.mean(0.5 * z ** 2 + np.log(s) + 0.5 * np.log(2 * np.pi))),
        "within_1s": float(np.mean(z < 1)), "within_2s": float(np.mean(z < 2)), "within_3s": float(np.mean(z < 3)),
    }


# expected fractions within 1/2/3 sigma: Gaussian with standard deviation sigma, Laplacian with scale sigma
# (the calibrated mean Mahalanobis distance of 1 is the Laplacian's E|x|/b)
EXPECTED_WITHIN = {"gauss": (0.6827, 0.9545, 0.9973),
                   "laplace": tuple(float(1 - np.exp(-n)) for n in (1, 2, 3))}
