"""The per-frame visual-inertial core that the frontend's fast path and the back end's keyframe window share:
cameras, IMU pre-integration and vision factors, the motion-only solve, the window's rules, the config they agree on."""
