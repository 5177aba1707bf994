"""The frontend's keyframe descriptors (ORB at the tracked features) and their ``frontend/keyframe_features``
message (for loop closure)."""

from __future__ import annotations

import numpy as np

from services.frontend.frames import KeyframeDescriptors
from shared.messages import Header, KeyframeFeatures


def describe_keyframe(orb, keyframe_id: int, stamp_ns: int, tracks: list[tuple[np.ndarray, np.ndarray]],
                      images: list[np.ndarray]) -> KeyframeDescriptors | None:
    """ORB descriptors of each camera's tracked features (``tracks``: per camera (ids, uv)) in its image; None when
    no feature could be described."""
    import cv2  # here: reading the frontend's process description must not load OpenCV

    ids_all, cams_all, uv_all, desc_all = [], [], [], []
    for i, ((ids, uv), img) in enumerate(zip(tracks, images)):
        kps = [cv2.KeyPoint(float(u), float(v), 31.0, -1.0, 0.0, 0, k) for k, (u, v) in enumerate(uv)]
        if not kps:
            continue
        kps, desc = orb.compute(img, kps)
        if desc is None or not kps:
            continue
        idx = np.array([kp.class_id for kp in kps], np.int64)
        ids_all.append(ids[idx])
        cams_all.append(np.full(len(idx), i, np.int16))
        uv_all.append(uv[idx])
        desc_all.append(desc)
    if not ids_all:
        return None
    return KeyframeDescriptors(keyframe_id, int(stamp_ns), np.concatenate(ids_all), np.concatenate(cams_all),
                               np.concatenate(uv_all), np.concatenate(desc_all))


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
