"""Named replica profiles: settings that make replicas harder, as the real images are (``sigmaslam synth
--profile NAME``, ``sigmaslam eval suite --profile NAME``; cached replicas get ``-NAME`` in their folder name).

``hard``: what the real EuRoC frames have and the default replicas do not:

- motion blur over an 8 ms exposure (the recorded exposure times are not part of the EuRoC files; 8 ms is an
  assumption for the MT9V034's auto exposure indoors at 20 Hz: 1-3 px of blur at the sequences' typical
  0.5-1 rad/s, more in their fastest turns), rendered by resampling along the image motion (7 samples);
- auto-exposure jumps: sudden gain changes, 0.1 per second per camera, each by a factor in [0.78, 1.28];
- a camera-IMU clock offset of 1 ms left in the data (the estimator assumes none).
"""

from __future__ import annotations

import dataclasses

from services.app.synth.replica import ReplicaSpec

PROFILES: dict[str, dict] = {
    "hard": {"render": {"motion_blur_samples": 7, "motion_blur_mode": "flow", "exposure_time_s": 0.008,
                        "exposure_jump_rate_hz": 0.1, "exposure_jump_amplitude": 0.25},
             "timeshift_cam_imu_s": 0.001},
}


def profile_settings(name: str) -> dict:
    """The settings of profile ``name`` ('' = none): ``{"render": {RenderConfig fields}, ReplicaSpec fields...}``."""
    if not name:
        return {}
    if name not in PROFILES:
        raise ValueError(f"unknown replica profile {name!r}; known: {', '.join(PROFILES)}")
    return PROFILES[name]


def apply_profile(spec: ReplicaSpec, name: str) -> ReplicaSpec:
    """``spec`` with the settings of profile ``name`` ('' = unchanged)."""
    p = profile_settings(name)
    render = dataclasses.replace(spec.render, **p.get("render", {}))
    return dataclasses.replace(spec, render=render, **{k: v for k, v in p.items() if k != "render"})
