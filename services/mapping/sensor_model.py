"""The piecewise-linear inverse sensor model of eq. 3 and the per-pixel sigma/tau it uses.

Sign convention: ``d_r`` is the distance along the ray of a point *behind* the measured surface
(negative in front of it, towards the camera). Eq. 3 as printed reads ``l_min / (3 sigma) * d_r``;
for the model to be continuous at ``d_r = -3 sigma`` (l = l_min there, l = 0 at the surface) the
slope must be ``-l_min / (3 sigma)``, which is what is used here, so that

- ``d_r < -3 sigma``:        l = l_min (free),
- ``-3 sigma <= d_r < tau/2``: l = -l_min * d_r / (3 sigma) (crosses 0 at the measurement),
- ``tau/2 <= d_r < tau``:    l = l_max = -l_min * tau / (6 sigma) (continuity),
- ``d_r >= tau``:            no update (occluded: unknown stays unknown).

tau is proportional to the depth as in the paper, and in addition at least ``tau_sigma_k`` (6) sigma_d
(:func:`surface_thickness`): with tau / 2 < 3 sigma the occupied side saturates at l_max < |l_min| and stops
at tau, while the free side reaches l_min, so the mean of eq. 4 over noisy depths crosses zero *behind* the
surface (a few mm at the stereo network's noise, up to ~1.5 cm at 5 cm noise with tau = 7.5 cm), which biased
the occupancy-to-point factors (docs/o2p.md). With tau >= 6 sigma the ramp is symmetric about the measurement.

The magnitude of the slope, ``|l_min| / (3 sigma)``, is the ``||grad L||`` that eq. 7 turns back into
``sigma_map = l_min / ||3 grad L||``.
"""

from __future__ import annotations

import numpy as np

from services.mapping.config import SensorModelConfig


def log_odds(d_r: np.ndarray, sigma: np.ndarray, tau: np.ndarray, l_min: float) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 3 (vectorised reference): log-odds and a mask of points that get an update."""
    d_r, sigma, tau = np.broadcast_arrays(np.asarray(d_r, float), np.asarray(sigma, float), np.asarray(tau, float))
    three_s = 3.0 * sigma
    l = np.where(d_r < -three_s, l_min, np.where(d_r < 0.5 * tau, -l_min * d_r / three_s, -l_min * 0.5 * tau / three_s))
    return l, d_r < tau


def surface_thickness(depth: np.ndarray, cfg: SensorModelConfig, sigma: np.ndarray | float = 0.0) -> np.ndarray:
    """tau [m]: proportional to depth, at least ``tau_sigma_k`` sigma_d, clamped to tau_min_m..tau_max_m."""
    tau = np.maximum(cfg.tau_k * np.asarray(depth, float), cfg.tau_sigma_k * np.asarray(sigma, float))
    return np.clip(tau, cfg.tau_min_m, cfg.tau_max_m)


def prepare_depth(depth: np.ndarray, sigma: np.ndarray | None, cfg: SensorModelConfig) -> tuple[np.ndarray, np.ndarray, int]:
    """Depth and sigma (float32, NaN where unusable) after the range limits and the configured sigma
    model; also the number of usable pixels. Raises ValueError on mismatched shapes."""
    depth = np.asarray(depth, np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth must be (H, W), got {depth.shape}")
    if cfg.sigma_model == "input":
        if sigma is None:
            raise ValueError("sigma_model 'input' needs a sigma image")
        sigma = np.asarray(sigma, np.float32)
        if sigma.shape != depth.shape:
            raise ValueError(f"sigma {sigma.shape} and depth {depth.shape} differ in shape")
    elif cfg.sigma_model == "linear":
        sigma = cfg.k_sigma * depth
    else:
        sigma = cfg.k_sigma * depth * depth
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(depth) & np.isfinite(sigma) & (depth >= cfg.near_m) & (depth <= cfg.max_depth_m) & (sigma > 0)
    d = np.where(ok, depth, np.nan).astype(np.float32)
    s = np.where(ok, np.clip(sigma, cfg.sigma_min_m, cfg.sigma_max_m), np.nan).astype(np.float32)
    return d, s, int(ok.sum())
