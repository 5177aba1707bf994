"""Dataset player: replays an EuRoC ASL folder onto sensors/imu and sensors/frame (minimal version)."""
