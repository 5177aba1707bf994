"""The viewer's declared topics (its loop is in services/viewer/service.py: Zenoh callbacks store the latest data
in the scene model and a drawing loop pushes changes to the browser, so it is not driven by a runner)."""

from __future__ import annotations

from shared import topics
from shared.dataflow import Input, ProcessNode

SHOWN_TOPICS = (topics.STATE, topics.KEYFRAMES, topics.SUBMAP, topics.FRAME, topics.DEPTH_STEREO, topics.DEPTH_FUSED,
                topics.LANDMARKS, topics.STATS, topics.STREAM_END)


class ViewerNode(ProcessNode):
    name = "viewer"
    inputs = tuple(Input(t, "on_message", note="shown") for t in SHOWN_TOPICS)
    outputs = (topics.CONTROL,)
    output_notes = {topics.CONTROL.key: "the page's pause and resume buttons"}
