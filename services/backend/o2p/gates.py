"""The gates an occupancy-to-point factor passes before it enters a graph (:func:`consistency`): enough of its points
inside the target's observed field, and a whitened squared error that a chi-square test at ``o2p.gate_chi2_p``
accepts."""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.special import chdtri  # chi-square quantile: chi2.ppf(p, k) = chdtri(k, 1 - p) (scipy.stats takes ~1.7 s to import)

from services.backend.o2p.config import O2PConfig
from services.backend.o2p.factor import OccupancyToPoint


@dataclasses.dataclass(frozen=True)
class GateResult:
    """The gates' view of one factor at the estimate where it would enter the graph."""

    n_points: int
    n_valid: int  # points inside the target's observed field (and off saturated free space)
    chi2: float  # whitened squared error with the N_eff cap, as the graph would see it
    dof: float  # min(n_valid, N_eff) (n_valid without a cap)
    limit: float  # chi-square quantile at gate_chi2_p (inf without the gate)
    reason: str  # '' when accepted, else 'too_few_inside' | 'overlap' | 'chi2'


def consistency(f: OccupancyToPoint, T_WA: np.ndarray, T_WB: np.ndarray, cfg: O2PConfig,
                min_fraction: float | None = None) -> GateResult:
    """Overlap and chi-square gates of a freshly made factor ``f`` (before :meth:`OccupancyToPoint.factor`)
    at poses T_WA (points) and T_WB (target), both body poses in the window's frame.

    Overlap: >= ``min_points_in_field`` and >= ``min_fraction`` (default ``min_inside_fraction``; map-to-map
    passes 0: a submap starts where the previous one's overlap fell below mapping.submaps.eps_vol, so most of
    its points lie outside its target by design) of the points inside the observed field.
    Chi-square: with n valid points and whitened residuals r_i (eq. 6-7), the factor's squared error is
    s * sum r_i^2 with s = min(1, N_eff / n) (:meth:`OccupancyToPoint.row_scale`); for consistent depth, map
    and poses it follows roughly a chi-square with min(n, N_eff) degrees of freedom (N_eff independent pieces of
    information; the correlated remainder adds little spread), so above its ``gate_chi2_p`` quantile the points
    do not lie on the map at this estimate."""
    ev = f.evaluate(np.asarray(T_WA, float), np.asarray(T_WB, float))
    n, nv = len(f.p_A), int(ev.valid.sum())
    scale = f.row_scale(nv) / f.info_scale  # evaluate() ran with sqrt(info_scale) rows: the cap on top
    stat = float(scale * np.sum(ev.r**2))
    dof = float(min(nv, cfg.effective_points) if cfg.effective_points > 0 else nv)
    limit = float(chdtri(max(dof, 1.0), 1.0 - cfg.gate_chi2_p)) if cfg.gate_chi2_p > 0 else float("inf")
    if nv < cfg.min_points_in_field:
        reason = "too_few_inside"
    elif nv < (cfg.min_inside_fraction if min_fraction is None else min_fraction) * n:
        reason = "overlap"
    elif stat > limit:
        reason = "chi2"
    else:
        reason = ""
    return GateResult(n, nv, stat, dof, limit, reason)
