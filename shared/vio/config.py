"""The per-frame VIO core's config: what the back end's keyframe window and the frontend's fast path must agree
on (noise models, robust loss, solve, the keyframe rule) and the fast path's own settings.

:class:`VioConfig` is the common part of the ``backend`` section (``services/backend/config.py``:
``BackendConfig`` extends it with the window's own fields), so that one YAML section configures the estimator in
both processes and they cannot disagree: a process hands ``cfg.backend`` to the core as a :class:`VioConfig`.
"""

from __future__ import annotations

import dataclasses

from shared.config import param


@dataclasses.dataclass(frozen=True)
class VioConfig:
    """Noise models and solve of the per-frame VIO core, shared by the keyframe window and the fast path."""

    # --- keyframes and solve ---
    max_keyframe_interval_s: float = param(0.5, "a frame becomes a keyframe at the latest after this long", "s")
    lm_max_iterations: int = param(6, "Levenberg-Marquardt iterations per frame (the window's, and the fast path's Gauss-Newton)")
    lm_relative_error_tol: float = param(1e-4, "LM (and the fast path) stops when the relative cost decrease falls below this")
    sigma_px: float = param(1.0, "reprojection noise (1 sigma) of a feature observation", "px")
    cauchy_k: float = param(2.0, "Cauchy robust-loss scale, in units of sigma (whitened residual)")
    # --- IMU (continuous-time densities; an ImuCalib passed to the estimator overrides them) ---
    gravity_m_s2: float = param(9.81, "magnitude of gravity along -z of W", "m/s^2")
    gyro_noise_density: float = param(1.6968e-4 * 5, "gyro white-noise density (inflated over the datasheet)", "rad/s/sqrt(Hz)")
    accel_noise_density: float = param(2.0e-3 * 5, "accelerometer white-noise density (inflated)", "m/s^2/sqrt(Hz)")
    gyro_random_walk: float = param(1.9393e-5 * 5, "gyro bias random walk density", "rad/s^2/sqrt(Hz)")
    accel_random_walk: float = param(3.0e-3 * 5, "accelerometer bias random walk density", "m/s^3/sqrt(Hz)")
    integration_sigma: float = param(1e-4, "position integration noise density of the pre-integration", "m/s/sqrt(Hz)")
    # --- tracking status ---
    min_landmarks_tracking: int = param(6, "fewer triangulated landmarks observed in a frame than this: status 'imu_only'")
    # --- the fast path (in the frontend's process: every frame's state against the newest window) ---
    imu_wait_s: float = param(0.5, "how long a feature frame waits for the IMU samples up to its time", "s")
    fast_path_budget_ms: float = param(8.0, "per-frame budget of the fast path's motion-only solve (in the "
                                       "frontend's process, services/frontend/odometry.py; stats topic)", "ms")
    fast_path_settle_s: float = param(2.0, "for this long after the back end's first window (its start or a restart) "
                                      "the fast path solves the anchor keyframe's velocity and accelerometer bias "
                                      "with each frame, held by priors at the window's estimate, instead of pinning "
                                      "them: a window just initialised has not settled them, and pinned they drift "
                                      "the frames until the next window (0: always pinned)", "s")
    fast_path_settle_velocity_sigma: float = param(0.05, "... prior sigma of the anchor's velocity then", "m/s")
    fast_path_settle_acc_bias_sigma: float = param(0.1, "... of its accelerometer bias", "m/s^2")
    fast_path_settle_gyro_bias_sigma: float = param(0.001, "... of its gyroscope bias", "rad/s")
    fast_path_waits_for_window: bool = param(False, "the fast path waits (up to imu_wait_s) for the window of the "
                                             "keyframe before each frame: reproducible lockstep runs (sigmaslam run "
                                             "sets it without --realtime/--rate); off live, where no frame may wait")
