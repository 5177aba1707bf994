"""The Zenoh runner (transport/runner.py) with a slow node on a keep-latest trigger: over real Zenoh on loopback,
frames arrive faster than the node handles them, and the node must stay on the newest ones."""

from __future__ import annotations

import threading
import time

import numpy as np

from helpers_zenoh import router, wait_for
from shared import topics
from shared.dataflow import Input, ProcessNode
from shared.messages import Header, MultiCameraFrame
from transport.node import Node
from transport.runner import run_node


class SlowCounter(ProcessNode):
    """Takes 0.1 s per frame and keeps the stamps it handled; a keep-latest trigger without a shed method."""

    name = "slow_counter"
    inputs = (Input(topics.FRAME, "on_frame", role="trigger"),)  # the topic's policy: latest, depth 4
    outputs = ()

    def __init__(self) -> None:
        self.handled: list[int] = []
        self.backlogs: list[int] = []

    def on_frame(self, f):
        time.sleep(0.1)
        self.handled.append(int(f.header.stamp_ns))
        self.backlogs.append(self.backlog)


def _frame(k: int) -> MultiCameraFrame:
    t = 1_000_000_000 + k * 20_000_000
    return MultiCameraFrame(header=Header(stamp_ns=t, seq=k, frame_id="rig"), images=(np.zeros((2, 2), np.uint8),),
                            camera_names=("cam0",), stamps_ns=np.array([t], np.int64))


def test_a_slow_node_on_a_keep_latest_trigger_does_not_build_a_backlog():
    node, stop = SlowCounter(), threading.Event()
    assert topics.FRAME.queue_policy == "latest" and topics.FRAME.queue_depth == 4
    with router() as cfg:
        worker = threading.Thread(target=run_node, args=(node, cfg), kwargs={"stopped": stop.is_set}, daemon=True)
        worker.start()
        try:
            with Node("test_player", cfg) as tn:
                pub = tn.publisher(topics.FRAME)
                time.sleep(0.5)  # discovery
                n = 60
                for k in range(n):  # 50 frames per second for 1.2 s, against 10 the node can handle
                    pub.publish(_frame(k))
                    time.sleep(0.02)
                last = int(_frame(n - 1).header.stamp_ns)
                assert wait_for(lambda: last in node.handled, timeout=20.0), node.handled
                time.sleep(0.3)
        finally:
            stop.set()
            worker.join(timeout=5.0)
    assert node.handled == sorted(node.handled)
    # taking every frame that left the queue (the old runner) handles ~48 of 60, each later than the one before;
    # keeping the newest 4 leaves ~12 handled while frames come plus at most 4 behind
    assert len(node.handled) <= 30, len(node.handled)
    assert node.handled[-1] == last
    # the node is told how many frames waited when it took each one: behind while frames come, none at the end
    assert max(node.backlogs) >= 1 and node.backlogs[-1] == 0
    assert max(node.backlogs) <= topics.FRAME.queue_depth
