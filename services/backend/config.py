"""Configuration of the visual-inertial back end: the per-frame core's (:class:`shared.vio.config.VioConfig`, which
the frontend's fast path reads too) and the keyframe window's own."""

from __future__ import annotations

import dataclasses

from shared.config import param
from shared.vio.config import VioConfig


@dataclasses.dataclass(frozen=True)
class BackendConfig(VioConfig):
    """Windowed visual-inertial smoother (gtsam): the core's settings (:class:`VioConfig`) and the window's."""

    # --- window and optimisation ---
    window_keyframes: int = param(8, "keyframes kept in the optimisation window (plus the latest frame)")
    # --- landmarks ---
    min_parallax_deg: float = param(1.0, "least ray angle between two observations to triangulate a landmark", "deg")
    max_reproj_error_px: float = param(4.0, "largest reprojection error of a triangulated or optimised landmark", "px")
    min_depth_m: float = param(0.1, "landmarks closer to a camera than this are rejected (cheirality)", "m")
    max_depth_m: float = param(60.0, "landmarks farther than this from every observing camera are rejected", "m")
    max_landmarks: int = param(400, "landmarks kept in the window at most (oldest dropped first)")
    max_published_landmarks: int = param(2000, "landmarks in one estimator/landmarks message at most (those seen "
                                         "most recently, then most often, are kept)")
    # --- monocular rig (rig.cameras names one camera; services/backend/window/still.py) ---
    mono_still_flow_px: float = param(1.0, "one camera: a frame whose features moved less than this (median, raw "
                                      "image motion) since the last keyframe stands still: relative-pose and "
                                      "zero-velocity factors keep the pose while nothing can be triangulated; "
                                      "0 = off", "px")
    still_stereo: bool = param(True, "rigs of two or more cameras get the same stand-still factors (first camera's "
                               "features; mono_still_*) until they first move: on a start from standing still the "
                               "window's velocity and biases settle at once instead of wandering for its first "
                               "keyframes (mid-run pauses: held marginals, not these)")
    mono_still_min_features: int = param(20, "one camera: features shared with the keyframe needed to call it still")
    mono_still_sigma_rot_rad: float = param(2e-3, "one camera: rotation sigma of the still relative-pose factor", "rad")
    mono_still_sigma_pos_m: float = param(2e-3, "one camera: translation sigma of the still relative-pose factor", "m")
    mono_still_sigma_vel_m_s: float = param(0.01, "one camera: sigma of the zero-velocity prior of a still frame", "m/s")
    mono_init_parallax_deg: float = param(2.0, "one camera, moving start: the window is rebuilt from two-view geometry "
                                          "and the IMU (services/backend/window/mono_init.py) once the oldest and newest "
                                          "keyframe's shared features have this median parallax", "deg")
    mono_init_min_features: int = param(30, "one camera, moving start: shared features needed for that rebuild")
    mono_init_speed_sigma_m_s: float = param(0.5, "one camera, moving start: until that rebuild, each new state gets a "
                                             "zero-velocity prior of this sigma so that the IMU alone cannot run away "
                                             "(0 = none)", "m/s")
    mono_init_ransac_px: float = param(1.0, "one camera, moving start: RANSAC threshold of the two-view geometry and "
                                       "PnP of the rebuild", "px")
    # --- online extrinsic refinement (services/backend/window/extrinsics.py) ---
    refine_extrinsics: bool = param(False, "estimate each camera's extrinsic T_SC in the window, starting from the "
                                    "calibration file's (its prior sigmas below); the refined T_SC is used by the "
                                    "fast path and written by `sigmaslam run` (extrinsics_refined.yaml)")
    extrinsic_prior_sigma_rot_deg: float = param(2.0, "how far the calibration's camera rotation may be off (1 sigma "
                                                 "per axis): the first prior on T_SC", "deg")
    extrinsic_prior_sigma_trans_m: float = param(0.02, "how far the calibration's camera position may be off (1 "
                                                 "sigma per axis)", "m")
    extrinsic_walk_rot_deg: float = param(0.005, "random walk of the camera rotation per keyframe: bounds how "
                                          "confident the carried T_SC prior gets (extrinsics.py)", "deg")
    extrinsic_walk_trans_m: float = param(5e-5, "random walk of the camera position per keyframe", "m")
    # --- online camera-IMU time offset (services/backend/window/time_offset.py) ---
    estimate_time_offset: bool = param(True, "estimate the camera-IMU time offset td (an image stamped t was taken at "
                                       "IMU time t + td) from the keyframes' residuals against their image motion; "
                                       "the frontend moves its published tracks by -td x their image velocity (on by "
                                       "default since stop 38: docs/results/README.md)")
    time_offset_sigma_ms: float = param(10.0, "how far the stamps may be off at the start (1 sigma)", "ms")
    time_offset_walk_ms: float = param(0.1, "random walk of the offset per keyframe", "ms")
    time_offset_rotation_sigma_deg: float = param(0.01, "noise of one keyframe interval's rotation, window against "
                                                  "gyro, in the offset's filter (time_offset.py)", "deg")
    time_offset_max_ms: float = param(50.0, "the estimate is clamped to +- this", "ms")
    # --- priors and initialisation ---
    prior_sigma_rot_rad: float = param(1e-3, "first state's roll/pitch/yaw prior after a static start", "rad")
    prior_sigma_tilt_moving_rad: float = param(0.03, "first state's roll/pitch prior after a moving start, until "
                                               "the gravity alignment (moving_align_after_s)", "rad")
    prior_sigma_tilt_aligned_rad: float = param(1e-3, "... and of the oldest state once the window was turned to its "
                                                "measured gravity: held firmly (a loosely held tilt wanders for "
                                                "seconds and bends the trajectory)", "rad")
    moving_align_after_s: float = param(1.0, "several cameras, moving start: once the window's keyframes span this "
                                        "long (or fill the window), gravity and the velocities are measured from them and the IMU and the "
                                        "window is turned to that gravity (services/backend/window/gravity_align.py; "
                                        "0 = never)", "s")
    moving_align_min_stereo: int = param(10, "... only when the newest keyframe sees at least this many landmarks in "
                                         "two cameras at once (without overlapping cameras vision has no scale of its "
                                         "own to tell the tilt by)")
    moving_align_min_travel_m: float = param(0.2, "... its free scale is the check when the cameras travelled this "
                                             "far over the window; below, the scale is held at 1 (a drone standing "
                                             "with its rotors running fails the static test, and shows no scale)", "m")
    moving_align_max_scale_error: float = param(0.1, "... the alignment is refused (and tried again at the next "
                                                "keyframe, up to 3x moving_align_after_s) when its free scale is off "
                                                "1 by more than this (relative)")
    prior_sigma_pos_m: float = param(1e-3, "first state's position prior", "m")
    prior_sigma_vel_m_s: float = param(0.01, "first state's velocity prior after a static start", "m/s")
    prior_sigma_vel_moving_m_s: float = param(1.0, "first state's velocity prior after a moving start", "m/s")
    prior_sigma_gyro_bias: float = param(5e-3, "initial gyro bias prior after a static start (the mean gyro reading)",
                                         "rad/s")
    prior_sigma_gyro_bias_moving: float = param(0.05, "initial gyro bias prior after a moving start (taken as zero: "
                                                "EuRoC's are up to 0.08 rad/s)", "rad/s")
    prior_sigma_acc_bias: float = param(0.1, "initial accelerometer bias prior", "m/s^2")
    marginals_landmark_sigma_m: float = param(10.0, "when the window's marginals are indeterminant (landmarks seen from "
                                              "one place only: a still body), they are computed again with priors "
                                              "of this sigma on the landmarks", "m")
    static_window_s: float = param(0.5, "IMU span inspected for a static start", "s")
    static_gyro_std: float = param(0.01, "a start is static when the gyro std stays below this", "rad/s")
    static_acc_std: float = param(0.15, "... and the accelerometer std below this", "m/s^2")
    static_lowpass_s: float = param(0.05, "the static test looks at the IMU readings averaged over blocks this long "
                                    "(motor vibration is not motion; 0 = raw readings)", "s")
    compute_covariance: bool = param(False, "compute the 15x15 marginal covariance of every frame (else only of "
                                     "keyframes, NaN for the others; ~5-10 ms per frame)")
    reject_outliers_every_frame: bool = param(False, "remove outlier observations after every frame's optimisation "
                                              "(else only when the frame becomes a keyframe)")
    motion_only_between_keyframes: bool = param(True, "non-keyframe frames solve only their own state against the "
                                                "fixed window (ignored when compute_covariance is on)")
    # --- service ---
    budget_ms: float = param(18.0, "per-keyframe budget of the back end's window optimisation (stats topic)", "ms")
    max_backlog_frames: int = param(4, "back end: when more feature frames than this wait, the oldest non-keyframes "
                                    "are skipped (it needs only keyframes; counted as drops); 0: never skip")
    max_backlog_keyframes: int = param(3, "back end: when more keyframes than this wait (its window optimisation "
                                       "slower than the keyframe rate for a while), the oldest are skipped too "
                                       "(counted as drops), so the fast path's window stays current; 0: never")
