"""Configuration of the feature frontend."""

from __future__ import annotations

import dataclasses

from shared.config import param


@dataclasses.dataclass(frozen=True)
class FrontendConfig:
    """Multi-camera KLT frontend."""

    # --- detection ---
    max_features_per_camera: int = param(160, "features tracked per camera at most")
    grid_cols: int = param(8, "detection grid columns (features are spread over the cells)")
    grid_rows: int = param(6, "detection grid rows")
    min_distance_px: float = param(15.0, "least distance between two features of one camera", "px")
    fast_threshold: int = param(20, "FAST corner threshold (intensity difference; lowered once when too few corners)")
    border_px: int = param(8, "no features closer than this to the image border", "px")
    # --- KLT tracking ---
    klt_window_px: int = param(15, "KLT window side", "px")
    klt_levels: int = param(3, "KLT pyramid levels above the full image")
    klt_iterations: int = param(10, "KLT iterations per level")
    klt_affine: bool = param(True, "refine the frame-to-frame tracks against the patch where each feature was first "
                             "seen, through an affine warp with gain and offset (services/frontend/affine_klt.py): "
                             "translation-only KLT drifts as a patch grows, shrinks, turns and changes brightness")
    affine_keyframes_only: bool = param(True, "refine at keyframes only (what the estimator's window sees; the next "
                                        "frames track on from the refined positions) instead of every frame: "
                                        "about a fifth of the CPU")
    affine_window_px: int = param(15, "side of that template (made odd)", "px")
    affine_iterations: int = param(6, "Gauss-Newton iterations of one affine refinement")
    affine_min_ncc: float = param(0.8, "least normalised cross-correlation of template and warped patch")
    affine_max_move_px: float = param(2.0, "the refined position is taken only within this of the KLT one", "px")
    affine_max_scale_change: float = param(1.5, "a template whose warp scales by more than this starts over")
    fb_max_error_px: float = param(0.7, "forward-backward tracking error above which a track is dropped", "px")
    fb_levels: int = param(0, "pyramid levels of the forward-backward check's return track (it starts where the "
                           "track began and must come back within fb_max_error_px: the full image suffices)")
    defer_detection: bool = param(True, "on a frame that is not a keyframe, while the estimator tracks, publish the "
                                  "tracked features first and detect and match new ones after (off the latency "
                                  "path; the window takes keyframes only, so it sees the same features). Needs "
                                  "kf_max_interval_s <= backend.max_keyframe_interval_s")
    keyframe_work_after_state: bool = param(True, "at a keyframe, while the estimator tracks, publish the frame's "
                                            "state from its tracked features first, then detect, match, refine and "
                                            "describe the keyframe's features and publish them (the back end's "
                                            "window needs them; the state does not): keyframes no longer cost the "
                                            "pose's latency ~15 ms more than other frames")
    skip_detection_when_behind: bool = param(True, "a live frontend whose next frame is already waiting when it "
                                             "takes a frame leaves out that frame's deferred detection (keyframes "
                                             "always detect; the window sees keyframes only), so it catches up "
                                             "instead of skipping frames; lockstep runs are never behind")
    opencv_threads: int = param(1, "OpenCV threads of the frontend process (its KLT, remap and FAST split each call "
                                "across them). 1: the frontend runs real-time (services/app/scheduling.py), and "
                                "OpenCV's workers, real-time too, would take every core at once and stall the back "
                                "end; 0: OpenCV's default, one per core")
    use_gyro_prior: bool = param(True, "start KLT at the position predicted by the gyro-integrated rotation")
    match_gain: bool = param(False, "before each KLT (frame to frame, camera to camera) scale the brighter image "
                             "of the pair to the darker one's mean grey level: KLT assumes constant brightness, "
                             "which auto-exposure jumps and left/right gain differences break (off: on whole "
                             "replicas it helps the hard profile and costs the plain one, docs/results/README.md; "
                             "replaces stop 39's running-level gain_time_constant_s)")
    match_gain_cross: bool = param(True, "match_gain for the camera-to-camera KLT of new features only: the "
                                   "cameras' auto exposure differs, and a left/right brightness difference leaves "
                                   "fewer stereo matches and biases the rest (hard MH_02: 20 % matched at 0.9 px "
                                   "median error -> 93 % at 0.2 px, docs/results/README.md, stop 41)")
    normalise_gain: bool = param(False, "scale every image to the same mean brightness before tracking and matching "
                                 "(KLT assumes constant brightness: auto-exposure jumps and left/right gain "
                                 "differences break it)")
    normalised_mean_dn: float = param(110.0, "the mean grey level images are scaled to with normalise_gain", "DN")
    # --- outlier rejection ---
    ransac_threshold_px: float = param(1.0, "fundamental-matrix RANSAC inlier threshold (undistorted pixels)", "px")
    ransac_confidence: float = param(0.995, "RANSAC confidence")
    ransac_min_flow_px: float = param(0.7, "skip RANSAC when the rotation-compensated median flow is below this", "px")
    # --- cross-camera matching ---
    stereo_init_depth_m: float = param(4.0, "depth assumed for the initial KLT guess in the other camera", "m")
    epipolar_max_px: float = param(1.5, "largest distance to the epipolar line of a cross-camera match", "px")
    stereo_recheck_px: float = param(0.5, "every frame, each landmark seen by two cameras is matched from the first "
                                     "into the second again with a small window, starting at the second camera's "
                                     "pixel; that observation is dropped when the two differ by more than this "
                                     "(0: off). Catches tracks that slid apart along the epipolar line and matches "
                                     "on occlusion edges", "px")
    stereo_recheck_window_px: int = param(7, "KLT window side of that re-check", "px")
    stereo_min_depth_m: float = param(0.2, "cross-camera matches triangulating closer than this are rejected", "m")
    min_view_overlap_cos: float = param(0.5, "cameras are matched only when their optical axes' cosine exceeds this")
    # --- keyframes ---
    kf_min_track_ratio: float = param(0.6, "keyframe when fewer than this share of the last keyframe's landmarks "
                                      "is still tracked")
    kf_min_parallax_px: float = param(15.0, "keyframe when the rotation-compensated median parallax since the last "
                                      "keyframe exceeds this", "px")
    kf_max_interval_s: float = param(0.5, "keyframe at the latest after this long", "s")
    # --- descriptors ---
    orb_descriptors: bool = param(True, "compute ORB descriptors of the tracked features at every keyframe")
    keyframe_store: int = param(2000, "keyframes whose descriptors are kept (oldest dropped first)")
    # --- service ---
    budget_ms: float = param(15.0, "per-frame budget of the tracking stage (stats topic)", "ms")
    imu_wait_s: float = param(0.05, "how long a frame waits for the gyro samples up to its time", "s")
    max_backlog_frames: int = param(2, "live: when more camera frames than this wait for the frontend process (it "
                                    "fell behind the sensor), the oldest are skipped (counted as drops; the next "
                                    "frame is tracked from the last one handled), so the pose latency stays bounded; "
                                    "0: never skip")

    def __post_init__(self) -> None:
        if not 5 <= self.affine_window_px <= 41:
            raise ValueError(f"frontend.affine_window_px must be 5..41, got {self.affine_window_px}")
        if self.max_backlog_frames < 0:
            raise ValueError(f"frontend.max_backlog_frames must be >= 0, got {self.max_backlog_frames}")
        if self.affine_iterations < 1:
            raise ValueError(f"frontend.affine_iterations must be >= 1, got {self.affine_iterations}")
        if not -1.0 <= self.affine_min_ncc <= 1.0:
            raise ValueError(f"frontend.affine_min_ncc must be in [-1, 1], got {self.affine_min_ncc}")
        if not self.affine_max_move_px > 0 or not self.affine_max_scale_change > 1.0:
            raise ValueError("frontend.affine_max_move_px must be > 0 and affine_max_scale_change > 1, got "
                             f"{self.affine_max_move_px}, {self.affine_max_scale_change}")
