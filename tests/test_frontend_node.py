"""The frontend process's node (services/frontend/node.py): a backlog behind the sensor is shed oldest first, and new
features are skipped only when the node is behind and asked to (the tracker alone: tests/test_frontend_tracker.py)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import frontend_scene as fs
from services.frontend.config import FrontendConfig
from test_frontend_tracker import DT


def test_a_frontend_process_behind_the_sensor_skips_its_oldest_frames():
    """Live, frames that wait beyond frontend.max_backlog_frames are skipped oldest first (the runner counts them as
    drops), so the pose latency stays bounded; 0 keeps every frame; a negative bound is refused."""
    from services.frontend.node import make_node
    from services.app.system_config import load_system_config
    from shared import topics

    cfg = load_system_config(None, [])
    node = make_node(cfg, fs.rig())
    trigger = next(i for i in node.inputs if i.role == "trigger")
    assert trigger.topic is topics.FRAME and getattr(node, trigger.shed) == node.shed  # the runner sheds through it
    pending = list(range(7))
    kept, skipped = node.shed(pending)
    bound = cfg.frontend.max_backlog_frames
    assert bound > 0 and kept == pending[-bound:] and skipped == 7 - bound
    assert node.shed(pending[:bound]) == (pending[:bound], 0)
    unbounded = make_node(load_system_config(None, ["frontend.max_backlog_frames=0"]), fs.rig())
    assert unbounded.shed(pending) == (pending, 0)
    with pytest.raises(ValueError, match="max_backlog_frames"):
        dataclasses.replace(FrontendConfig(), max_backlog_frames=-1)


@pytest.mark.parametrize("skip", [False, True])
def test_the_frontend_node_skips_detection_only_when_behind_and_asked_to(stereo_seq, skip):
    """FrontendNode.after_publish: with frontend.skip_detection_when_behind, a frame taken while the next one waited
    (the runner's ``backlog`` > 0) gets no new features; a frame taken on time always does, and so does every frame
    without the setting. The frames are tracked alone (FrontendNode.track: no fast path, whose placeholder states
    would say 'initialising')."""
    from services.frontend.node import make_node
    from services.app.system_config import load_system_config
    from shared.messages import Header, MultiCameraFrame

    room, cams, poses, images = stereo_seq
    cfg = load_system_config(None, ["frontend.kf_min_parallax_px=4.0",
                                    f"frontend.skip_detection_when_behind={str(skip).lower()}"])
    node = make_node(cfg, cams)
    node.estimator_status = "tracking"  # detection is deferred only while the estimator tracks
    done = {True: 0, False: 0}
    for k, ims in enumerate(images):
        t = int(round(k * DT * 1e9))
        node.track(MultiCameraFrame(header=Header(stamp_ns=t, seq=k, frame_id="rig"), images=tuple(ims),
                                    camera_names=tuple(node.names), stamps_ns=np.full(len(ims), t, np.int64)))
        behind = k % 4 == 1  # here every other frame is a keyframe: behind at half of the others
        pending = node.tracker.detection_pending
        node.backlog = int(behind)
        node.after_publish()
        assert not node.tracker.detection_pending
        done[behind] += pending
    assert done[True] > 0 and done[False] > 0
    assert node.tracker.totals["detection_skipped"] == (done[True] if skip else 0)
    assert node.counters()["detections_skipped"]() == (done[True] if skip else 0)  # in stats/frontend


def test_a_keyframe_state_goes_out_before_its_tracks_and_new_features(stereo_seq):
    """frontend.keyframe_work_after_state: at a keyframe, on_frame publishes the state alone (the tracked features
    give it) and after_publish the keyframe's descriptors and complete tracks, with the features it detected; without
    the setting on_frame publishes all three at once."""
    from services.frontend.node import make_node
    from services.app.system_config import load_system_config
    from shared import topics
    from shared.messages import Header, MultiCameraFrame

    room, cams, poses, images = stereo_seq
    seen = {}
    for after in (True, False):
        cfg = load_system_config(None, ["frontend.kf_min_parallax_px=4.0",
                                        f"frontend.keyframe_work_after_state={str(after).lower()}"])
        node = make_node(cfg, cams)
        keyframes = []
        for k, ims in enumerate(images):
            node.estimator_status = "tracking"  # the fast path here has no window: its states say 'initialising'
            t = int(round(k * DT * 1e9))
            first = node.on_frame(MultiCameraFrame(header=Header(stamp_ns=t, seq=k, frame_id="rig"),
                                                   images=tuple(ims), camera_names=tuple(node.names),
                                                   stamps_ns=np.full(len(ims), t, np.int64)))
            then = node.after_publish()
            kinds = [e.topic for e in first], [e.topic for e in then]
            feats = [e.msg for e in first + then if e.topic is topics.FEATURES]
            assert len(feats) == 1 and kinds[0][0] is topics.STATE
            if feats[0].is_keyframe and k > 0:
                keyframes.append((t, feats[0].landmark_ids.copy()))
                if after:
                    assert kinds == ([topics.STATE], [topics.KEYFRAME_FEATURES, topics.FEATURES]), kinds
                else:
                    assert kinds == ([topics.STATE, topics.KEYFRAME_FEATURES, topics.FEATURES], []), kinds
        seen[after] = keyframes
    assert len(seen[True]) >= 1 and [t for t, _ in seen[True]] == [t for t, _ in seen[False]]
    for (_, a), (_, b) in zip(seen[True], seen[False]):
        assert np.array_equal(a, b)  # the same tracks, new features included


def test_the_frontend_process_sets_its_opencv_threads_and_in_process_runs_keep_theirs():
    """frontend.opencv_threads is the frontend process's (its description's warm-up, which only a process of its own
    runs): building the node, as the in-process runner does beside depth's OpenCV, leaves OpenCV's threads alone."""
    import cv2

    from services.app.system_config import load_system_config
    from services.frontend.node import DESCRIPTION
    from shared.process_description import Start

    before = cv2.getNumThreads()
    try:
        cv2.setNumThreads(3)
        cfg = load_system_config(None, ["frontend.opencv_threads=1"])
        node = DESCRIPTION.build(cfg, Start(cameras=fs.rig()))
        assert cv2.getNumThreads() == 3
        DESCRIPTION.warm_up(node)
        assert cv2.getNumThreads() == 1
        cv2.setNumThreads(3)
        DESCRIPTION.warm_up(DESCRIPTION.build(load_system_config(None, ["frontend.opencv_threads=0"]),
                                              Start(cameras=fs.rig())))
        assert cv2.getNumThreads() == 3  # 0: OpenCV's own
    finally:
        cv2.setNumThreads(before)
