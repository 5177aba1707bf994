"""What the tracker gives per frame (:class:`TrackerOutput`) and per keyframe (:class:`KeyframeDescriptors`), and the
error of a frame it cannot use (:class:`FrontendInputError`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class FrontendInputError(ValueError):
    """Images that do not fit the rig (count, size, type) or time going backwards."""


@dataclass(frozen=True)
class KeyframeDescriptors:
    """ORB descriptors of the features of one keyframe (for loop-closure detection)."""

    keyframe_id: int
    stamp_ns: int
    landmark_ids: np.ndarray  # (K,) int64
    camera_index: np.ndarray  # (K,) int16
    uv: np.ndarray  # (K,2) float32, distorted pixels
    descriptors: np.ndarray  # (K,32) uint8, ORB


@dataclass(frozen=True)
class TrackerOutput:
    """Observations of one multi-camera frame (the fields of a FeatureFrame) and counters."""

    stamp_ns: int
    landmark_ids: np.ndarray  # (M,) int64
    camera_index: np.ndarray  # (M,) int16
    uv: np.ndarray  # (M,2) float32
    is_keyframe: bool
    keyframe_id: int  # -1 if not a keyframe
    counts: dict[str, int]
