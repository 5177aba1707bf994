"""The player's declared topics (its loop is in services/player/service.py: a source paced by the sensor clock,
the estimator's states in lockstep, or a rate; not driven by a runner)."""

from __future__ import annotations

from shared import topics
from shared.dataflow import Input, ProcessNode


class PlayerNode(ProcessNode):
    name = "player"
    inputs = (
        Input(topics.CONTROL, "on_control", note="pause, resume, stop"),
        Input(topics.STATE, "on_state", policy="latest", depth=64, when="--lockstep",
              note="the next frame after this one's state"),
        Input(topics.HEARTBEAT, "on_heartbeat", policy="all", depth=1000, when="--wait-for",
              note="the services are up before playing"),
    )
    outputs = (topics.IMU, topics.FRAME, topics.STREAM_END)
    output_notes = {topics.STREAM_END.key: "once, after the last frame"}
