"""Configuration of the depth service (``sigmaslam depth``): method, rate, rectification, networks, MVS views."""
from __future__ import annotations

import dataclasses
from typing import Literal

from shared.config import param


@dataclasses.dataclass(frozen=True)
class DepthConfig:
    """Stereo (+ MVS) depth with per-pixel sigma, fused by inverse variance (paper sec. IV-D)."""

    method: Literal["network", "sgbm"] = param("network", "'network' (stereo + MVS networks, fused) or 'sgbm' (OpenCV "
                                               "SGBM with heuristic sigma); 'network' falls back to 'sgbm' when the "
                                               "stereo weights are missing")
    rate_hz: float = param(10.0, "processing rate; newer frames replace older ones waiting (drops counted)", "Hz")
    left_camera: str = param("cam0", "rig camera used as the left (reference) camera")
    right_camera: str = param("cam1", "rig camera used as the right camera")
    width: int = param(512, "rectified image width (multiple of 16)", "px")
    height: int = param(384, "rectified image height (multiple of 16)", "px")
    fov_scale: float = param(1.0, "rectified focal length = left fx scaled to the new width / fov_scale")
    border_margin_px: int = param(8, "depth is dropped (NaN) on rectified pixels that no raw image covers (black "
                                  "rectification border) and within this distance of them: the networks make up "
                                  "depth there, MVS mostly far behind the true surface (docs/depth.md)", "px")
    max_relative_sigma: float = param(0.04, "pixels whose sigma exceeds this fraction of their depth are too "
                                      "uncertain to place a surface: every DepthFrame says so "
                                      "(surface_max_relative_sigma), the map takes only the free space well in front "
                                      "of them, and they are counted (docs/depth.md, 'Uncertain pixels'); 0: every "
                                      "pixel places its surface. Learned sigma only: SGBM's and the heuristic sigma "
                                      "grow with depth alone, and the rule would cut far depth")
    flying_radius_px: int = param(2, "pixels between the near and the far side of a depth edge within this distance "
                                  "are dropped (NaN) from every output and counted: the curtain a network draws "
                                  "across an object's silhouette (services/depth/flying.py); 0: keep them", "px")
    flying_rel_jump: float = param(0.04, "a depth edge: the depth around a pixel spans more than this fraction of its "
                                   "depth ...")
    flying_min_gradient: float = param(0.15, "... and its disparity changes by more than this per pixel (a far floor "
                                       "seen at a grazing angle changes by less)", "px/px")
    flying_margin: float = param(0.15, "a flying pixel lies more than this fraction of the edge's span from both its "
                                 "near and its far side")
    stereo_weights: str = param("", "stereo network weights (.pt with .json beside); '' = services/depth/weights/"
                                "stereo_refine.pt (the SGBM-guided network, real photographs and replicas alike); a "
                                "bare name = that file there (stereo.pt: the older network trained on rendered rooms "
                                "only, half the CPU, far worse on real images)")
    mvs_weights: str = param("", "MVS network weights; '' = services/depth/weights/mvs.pt, a bare name = that file there")
    mono: bool = param(False, "cam0 only (left_camera): MVS depth on posed keyframes alone, no stereo network and "
                       "no right image; the MVS depth goes out on depth/fused and depth/stereo (source 'mvs'), frames "
                       "before MVS has source views publish nothing (counted)")
    use_mvs: bool = param(True, "run the MVS network on posed keyframes and fuse it with stereo (method 'network')")
    fusion_correlation: float = param(0.23, "correlation of the stereo and MVS networks' normalised errors that the "
                                      "fusion assumes (0: eq. 14, independent errors; fitted on the validation split "
                                      "by python -m tools.depth.fit_fusion, docs/depth.md)")
    mvs_sources: int = param(4, "source views of the MVS network (1-7; 4 keeps the CPU time bounded)")
    mvs_min_baseline_m: float = param(0.03, "least distance between any two MVS views", "m")
    mvs_max_baseline_m: float = param(1.0, "largest distance of a source view from the reference", "m")
    mvs_max_angle_deg: float = param(35.0, "largest angle between the optical axes of source and reference", "deg")
    prior_max_points: int = param(300, "landmark pixels in the MVS network's sparse depth prior at most (trained "
                                  "with 20-300; 0: no prior)")
    prior_max_age_s: float = param(1.0, "landmarks enter the prior only when last seen within this long of the "
                                   "frame (older ones may be occluded)", "s")
    keyframe_views: int = param(12, "posed keyframe images kept as MVS source candidates")
    frame_history: int = param(60, "recent raw left images kept to attach to keyframes announced later")
    pose_wait_s: float = param(0.1, "how long a frame waits for its estimator state before going out unposed", "s")
    mono_pose_wait_s: float = param(0.5, "depth.mono: how long a frame waits for its estimator state (without one "
                                    "it has no MVS depth at all)", "s")
    sgbm_num_disparities: int = param(96, "SGBM disparity search range (multiple of 16)", "px")
    sgbm_block_size: int = param(5, "SGBM block size (odd)", "px")
    heuristic_sigma_model: Literal["quadratic", "linear"] = param("quadratic", "SGBM sigma model: 'quadratic' (constant "
                                                                  "disparity sigma, eq. 11) or 'linear' (relative depth sigma)")
    heuristic_sigma_coeff: float = param(1.0, "disparity sigma [px] for 'quadratic'; relative sigma [-] for 'linear'")
    stereo_sigma: Literal["network", "heuristic"] = param("network", "sigma of the stereo network's depth: 'network' "
                                                          "(its learned disparity sigma times the calibration gain, "
                                                          "eq. 11) or 'heuristic' (heuristic_sigma_model with "
                                                          "heuristic_sigma_coeff, as SGBM's: the paper's heuristic-"
                                                          "sigma row, Table IV); published on depth/stereo and fused")
    device: Literal["auto", "cpu", "cuda"] = param("auto", "where the networks run ('auto': CUDA when present)")
    threads: int = param(2, "CPU threads of the networks")
    stereo_precision: Literal["auto", "float32", "bfloat16"] = param(
        "auto", "arithmetic of the stereo network: 'bfloat16' = torch CPU autocast (convolutions and matrix products "
        "in bfloat16, softmax and outputs in float32), 2x faster on CPUs with AMX or AVX512-BF16 at the same accuracy "
        "(docs/depth.md); 'auto' = bfloat16 on such a CPU, float32 elsewhere (and on CUDA). MVS stays float32")
    budget_ms: float = param(100.0, "budget of one depth frame (networks + fusion), reported in stats", "ms")
    inject_delay_ms: float = param(0.0, "TEST/BENCH KNOB: extra sleep added to every depth frame inside the timed "
                                   "stage, to overload the service on purpose (docs/reliability.md); keep 0", "ms")

    def __post_init__(self) -> None:
        if self.width % 16 or self.height % 16 or self.width <= 0 or self.height <= 0:
            raise ValueError(f"depth.width/height must be positive multiples of 16, got {self.width}x{self.height}")
        if not 1 <= self.mvs_sources <= 7:
            raise ValueError(f"depth.mvs_sources must be 1..7, got {self.mvs_sources}")
        if self.mono and (self.method != "network" or not self.use_mvs):
            raise ValueError("depth.mono needs depth.method 'network' and depth.use_mvs (MVS is its only depth)")
        if self.border_margin_px < 0:
            raise ValueError(f"depth.border_margin_px must be >= 0, got {self.border_margin_px}")
        if self.rate_hz <= 0:
            raise ValueError("depth.rate_hz must be positive")
        if self.prior_max_points < 0 or not self.prior_max_age_s >= 0:
            raise ValueError(f"depth.prior_max_points and depth.prior_max_age_s must be >= 0, got "
                             f"{self.prior_max_points}, {self.prior_max_age_s}")
        if (self.flying_radius_px < 0 or not self.flying_rel_jump > 0 or not self.flying_min_gradient >= 0
                or not 0 <= self.flying_margin < 0.5):
            raise ValueError("depth.flying_radius_px >= 0, flying_rel_jump > 0, flying_min_gradient >= 0 and 0 <= "
                             f"flying_margin < 0.5 are required, got {self.flying_radius_px}, {self.flying_rel_jump}, "
                             f"{self.flying_min_gradient}, {self.flying_margin}")
        if not self.max_relative_sigma >= 0:
            raise ValueError(f"depth.max_relative_sigma must be >= 0, got {self.max_relative_sigma}")
        if self.inject_delay_ms < 0:
            raise ValueError(f"depth.inject_delay_ms must be >= 0, got {self.inject_delay_ms}")
