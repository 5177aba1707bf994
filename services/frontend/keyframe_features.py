"""The frontend's keyframe descriptors as a ``frontend/keyframe_features`` message (for loop closure)."""

from __future__ import annotations

import numpy as np

from shared.messages import Header, KeyframeFeatures


def keyframe_features_message(tracker, stamp_ns: int, seq: int = 0) -> KeyframeFeatures | None:
    """Message of the tracker's newest keyframe if it is the one at ``stamp_ns`` (None otherwise)."""
    store = getattr(tracker, "keyframe_descriptors", None)
    if not store:
        return None
    kd = store[-1]
    if int(kd.stamp_ns) != int(stamp_ns) or len(kd.landmark_ids) == 0:
        return None
    n = len(kd.landmark_ids)
    return KeyframeFeatures(header=Header(stamp_ns=int(stamp_ns), seq=seq, frame_id="rig"),
                            keyframe_id=int(kd.keyframe_id), landmark_ids=np.asarray(kd.landmark_ids, np.int64),
                            camera_index=np.asarray(kd.camera_index, np.int16),
                            uv=np.ascontiguousarray(kd.uv, np.float32).reshape(n, 2),
                            descriptors=np.ascontiguousarray(kd.descriptors, np.uint8).reshape(n, 32))
