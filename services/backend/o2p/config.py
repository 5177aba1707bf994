"""Configuration of the occupancy-to-point factors (paper eq. 5-7, sec. IV-C) in the back end."""

from __future__ import annotations

import dataclasses

from shared.config import param


@dataclasses.dataclass(frozen=True)
class O2PConfig:
    """Frame-to-map and map-to-map occupancy-to-point factors; off until shown to help."""

    enabled: bool = param(False, "add occupancy-to-point factors to the back end's window (needs map/field and depth)")
    frame_to_map: bool = param(True, "frame-to-map: live stereo depth of a window keyframe against its o(k)")
    map_to_map: bool = param(False, "map-to-map: fused-depth points of a finished submap m against o(m), between the two "
                             "submaps' anchor keyframes in the loop closer's pose graph and final BA (needs loop.enabled "
                             "and mapping.o2p_points > 0; why off: docs/o2p.md)")
    max_points_frame: int = param(200, "points per frame-to-map factor at most (the lowest-sigma ones)")
    max_points_map: int = param(1000, "points per map-to-map factor at most (the lowest-sigma ones)")
    min_points_in_field: int = param(100, "M_min: a target submap needs this many points inside its observed field")
    min_target_age_s: float = param(0.0, "frame-to-map: a target submap must have been finished at least this long before "
                                    "the frame (0: before the frame, so never a submap holding the frame's own depth or "
                                    "later depth, which pull the frame towards itself); > 0 keeps the factors for "
                                    "revisits (docs/o2p.md)", "s")
    map_target_gap_s: float = param(0.0, "map-to-map: o(m) must have been finished at least this long before m began "
                                    "(0: any older submap, nearly always m's predecessor)", "s")
    min_covisible_landmarks: int = param(5, "landmarks a frame must share with a submap to count it covisible")
    tukey_k: float = param(3.0, "Tukey threshold on the RMS whitened residual of a whole factor")
    info_scale: float = param(1.0, "scales the information of every point on top of effective_points (1: none; for experiments)")
    effective_points: float = param(10.0, "N_eff: a factor carries at most the information of this many independent points "
                                    "(depth errors are correlated across an image; rows scaled by min(1, N_eff / n_valid)); "
                                    "0: no cap (eq. 7 as it is); why 10: docs/o2p.md")
    grad_min: float = param(1.0, "points where |grad L| is below this (saturated free space) drop out", "1/m")
    depth_stamp_tolerance_ms: float = param(1.0, "a depth frame belongs to the window state with this stamp", "ms")
    attach_tolerance_ms: float = param(150.0, "a depth frame without a window state at its stamp attaches to the nearest "
                                       "window state this close, moved there by the relative pose of the two estimates "
                                       "(depth runs at ~10 Hz, keyframes are sparser; 0: exact stamps only)", "ms")
    anchor_tolerance_ms: float = param(1000.0, "map-to-map: a submap follows the keyframe nearest its creation within this "
                                       "(as mapping.submaps.keyframe_bind_tolerance_s)", "ms")
    gate_chi2_p: float = param(0.999, "consistency gate: a factor whose whitened squared error at the current estimate "
                               "(rows capped by N_eff, as it would enter the graph) exceeds the chi-square quantile of "
                               "this probability, with min(n_valid, N_eff) degrees of freedom, is rejected before it "
                               "enters the graph (counted gated_chi2); 0: no gate")
    min_inside_fraction: float = param(0.5, "overlap gate: share of a frame-to-map factor's points that must lie inside "
                                       "the target's observed field at the current estimate, besides M_min (counted "
                                       "gated_overlap; map-to-map terms need M_min only: consecutive submaps overlap "
                                       "little by design)")
    mono_settle_s: float = param(1.0, "one camera: dense factors wait this long after the window got its metric hold "
                                 "(it stood still, or services/backend/window/mono_init.py rebuilt it); depth frames and "
                                 "submaps begun before then are never used (their poses had no scale)", "s")
    max_pending_depth: int = param(32, "depth frames waiting for their window state at most (oldest dropped)")
    max_submaps: int = param(500, "finished submap fields kept at most (oldest dropped)")
    landmark_history_s: float = param(600.0, "landmark ids of past frames kept this long for covisibility", "s")

    def check(self) -> None:
        if min(self.max_points_frame, self.max_points_map, self.min_points_in_field, self.max_pending_depth,
               self.max_submaps) < 1:
            raise ValueError("o2p point counts and buffer sizes must be >= 1")
        if not (0 <= self.gate_chi2_p < 1 and 0 <= self.min_inside_fraction <= 1 and self.mono_settle_s >= 0
                and self.min_target_age_s >= 0 and self.map_target_gap_s >= 0):
            raise ValueError("o2p gate_chi2_p in [0, 1), min_inside_fraction in [0, 1], mono_settle_s >= 0, "
                             "min_target_age_s >= 0 and map_target_gap_s >= 0 are required")
        if not (self.tukey_k > 0 and self.grad_min >= 0 and self.info_scale > 0 and self.effective_points >= 0):
            raise ValueError("o2p tukey_k > 0, grad_min >= 0, info_scale > 0 and effective_points >= 0 are required")
