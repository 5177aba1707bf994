"""Choice of the MVS source views among posed keyframes (paper sec. V-A: baselines of 3 or 10 cm).

Walking from the newest candidate to the oldest, a candidate is taken when its camera centre is at least
``min_baseline_m`` from the reference and from every view taken so far (so the chosen set spans a range
of baselines), at most ``max_baseline_m`` from the reference, and its optical axis within
``max_angle_deg`` of the reference's.
"""
from __future__ import annotations

import numpy as np


def select_sources(T_W_ref: np.ndarray, T_W_cands: np.ndarray, n_max: int, min_baseline_m: float = 0.03,
                   max_baseline_m: float = 1.0, max_angle_deg: float = 35.0) -> np.ndarray:
    """Indices into ``T_W_cands`` (K,4,4), newest last, of up to ``n_max`` source views (newest first)."""
    T_W_cands = np.asarray(T_W_cands, np.float64).reshape(-1, 4, 4)
    c_ref = T_W_ref[:3, 3]
    z_ref = T_W_ref[:3, 2]
    centres = T_W_cands[:, :3, 3]
    dist = np.linalg.norm(centres - c_ref, axis=1)
    cos = T_W_cands[:, :3, 2] @ z_ref
    ok = (dist >= min_baseline_m) & (dist <= max_baseline_m) & (cos >= np.cos(np.radians(max_angle_deg)))
    chosen: list[int] = []
    for i in range(len(T_W_cands) - 1, -1, -1):  # over the few candidate keyframes, not pixels
        if len(chosen) >= n_max:
            break
        if ok[i] and all(np.linalg.norm(centres[i] - centres[j]) >= min_baseline_m for j in chosen):
            chosen.append(i)
    return np.array(chosen, dtype=np.int64)
