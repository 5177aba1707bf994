"""The map-to-map term of eq. 5 (:class:`MapToMap`): the points of a closed submap against the field of the submap
it overlaps, between the keyframes anchoring the two; the loop closer adds it to its pose graph and to the final
bundle adjustment."""

from __future__ import annotations

import dataclasses
import logging

import gtsam
import numpy as np

from services.backend.o2p.config import O2PConfig
from services.backend.o2p.factor import OccupancyToPoint
from services.backend.o2p.gates import GateResult, consistency
from shared.occupancy.query import BlockField

log = logging.getLogger("sigmaslam.backend.o2p")


@dataclasses.dataclass(frozen=True)
class MapToMap:
    """Map-to-map term of eq. 5: the points of submap m (in M_m) against the field of o(m), between the
    keyframes anchoring the two submaps (``T_KM``: a submap's frame in its anchor keyframe's body frame)."""

    submap: int
    target: int
    state_m: int
    state_o: int
    T_KM_m: np.ndarray
    T_KM_o: np.ndarray
    points_M: np.ndarray  # (N, 3) [m]
    sigma: np.ndarray  # (N,) [m]
    field: BlockField  # of o(m), in M_o
    l_min: float
    cfg: O2PConfig

    def build(self, key_m: int, key_o: int, T_WK_m: np.ndarray, T_WK_o: np.ndarray) -> gtsam.NonlinearFactor | None:
        """The factor between gtsam Pose3 keys of the two anchors (body poses), with its Tukey threshold set
        by the points inside o's field at the given anchor poses; None when the gates (:func:`consistency`)
        reject it there (fewer than M_min points inside, too little overlap, or chi-square)."""
        return self.gated_build(key_m, key_o, T_WK_m, T_WK_o)[0]

    def gated_build(self, key_m: int, key_o: int, T_WK_m: np.ndarray,
                    T_WK_o: np.ndarray) -> tuple[gtsam.NonlinearFactor | None, GateResult]:
        """:meth:`build` and the gates' verdict (``reason`` says why a None factor was rejected)."""
        c = self.cfg
        p_A = self.points_M @ self.T_KM_m[:3, :3].T + self.T_KM_m[:3, 3]
        f = OccupancyToPoint(self.field, self.l_min, p_A, self.sigma, key_a=key_m, key_b=key_o, T_BM=self.T_KM_o,
                             tukey_k=c.tukey_k, grad_min=c.grad_min, info_scale=c.info_scale,
                             effective_points=c.effective_points)
        g = consistency(f, T_WK_m, T_WK_o, c, min_fraction=0.0)
        if g.reason:
            log.info("o2p map-to-map %d -> %d rejected (%s): %d/%d points inside, chi2 %.1f (limit %.1f, dof %.0f)",
                     self.submap, self.target, g.reason, g.n_valid, g.n_points, g.chi2, g.limit, g.dof)
            return None, g
        return f.factor(g.n_valid), g
