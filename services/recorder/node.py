"""The recorder's declared topics: every topic of the namespace (one wildcard subscription, raw bytes to MCAP;
services/recorder/service.py)."""

from __future__ import annotations

from shared import topics
from shared.dataflow import Input, ProcessNode


class RecorderNode(ProcessNode):
    name = "recorder"
    inputs = tuple(Input(t, "on_sample", policy="all") for t in topics.ALL)
    outputs = ()
