"""Configuration of the dataset player (``sigmaslam player``)."""

from __future__ import annotations

import dataclasses
from typing import Literal

from shared.config import param


@dataclasses.dataclass(frozen=True)
class PlayerConfig:
    """How the player paces a dataset onto sensors/imu and sensors/frame.

    Modes: ``lockstep`` publishes the next frame only once the estimator answered the previous one
    (an estimator/state with a stamp >= the frame's) or ``lockstep_timeout_s`` passed: deterministic
    offline runs at whatever speed the pipeline manages. ``rate`` plays at ``rate`` x sensor time.
    """

    mode: Literal["lockstep", "rate"] = param("lockstep", "'lockstep' (wait for estimator/state per frame) or 'rate' (timed by rate)")
    rate: float = param(1.0, "mode 'rate': playback speed as a multiple of sensor time (1 = real time)")
    lockstep_timeout_s: float = param(3.0, "mode 'lockstep': longest wait for the estimator's answer to a frame", "s")
    start_paused: bool = param(False, "wait for a 'resume' control command before the first message")
    max_frames: int = param(0, "stop after this many frames (0 = all)")
    start_s: float = param(0.0, "begin this long after the first frame, as if the sensors were switched on there "
                           "(a start in mid-flight); earlier frames and IMU samples are not played", "s")
    end_linger_s: float = param(0.5, "stay on the bus this long after publishing sensors/end", "s")
    imu_margin_s: float = param(1.0, "EuRoC folders: play IMU samples only from this long before the first camera "
                                "frame to this long after the last (a trimmed folder may hold minutes of IMU "
                                "around seconds of images); negative: every sample", "s")

    def __post_init__(self) -> None:
        if not self.rate > 0 or not self.lockstep_timeout_s > 0:
            raise ValueError(f"player.rate and player.lockstep_timeout_s must be positive, got {self.rate}, "
                             f"{self.lockstep_timeout_s}")
        if self.max_frames < 0 or self.end_linger_s < 0 or self.start_s < 0:
            raise ValueError("player.max_frames, player.end_linger_s and player.start_s must be >= 0")

    def messages(self, source):
        """``source``'s messages (a player source or an EuRoC folder's reader) within the IMU margin, from the start
        this config asks for."""
        return source.messages(None if self.imu_margin_s < 0 else int(round(self.imu_margin_s * 1e9)),
                               int(round(self.start_s * 1e9)))
