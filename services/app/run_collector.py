"""What ``sigmaslam run`` reads from the bus while the pipeline runs: a declared node (:class:`RunCollectorNode`),
so the topic graph shows what the run reads, and its subscriptions are made from the declaration
(:func:`subscribe`): the graph cannot drift from what runs. :func:`collect` keeps the states, the last stats of each
process and the arrival times of frames and states until the stream has ended and the last state is in."""

from __future__ import annotations

import dataclasses
import threading
import time

import numpy as np

from services.app.metrics.latency import ArrivalLog
from shared import topics
from shared.dataflow import Input, ProcessNode
from transport.node import Node
from transport.queues import Empty

PROGRESS_EVERY_S = 10.0  # wall time between two progress lines of a run [s]


class RunCollectorNode(ProcessNode):
    """The run's reader of the bus; its inputs' handlers are :class:`Collection` methods (called in Zenoh's threads)
    or, without one, queues :func:`collect` drains."""

    name = "run"
    inputs = (
        Input(topics.STATE, "states", policy="all", depth=1_000_000, note="every state: the trajectory files"),
        Input(topics.FRAME, "on_frame_arrival", policy="latest", depth=1, note="arrival times: the pose latency"),
        Input(topics.STATE, "on_state_arrival", policy="latest", depth=1, note="arrival times: the pose latency"),
        Input(topics.STATS, "stats", policy="all", depth=10_000, note="stats.json"),
        Input(topics.STREAM_END, "ends", note="the player's end: the run stops after the last state"),
        Input(topics.WINDOW, "on_window", policy="latest", depth=1, note="refined extrinsics, time offset"),
        Input(topics.TRAJECTORY_FINAL, "finals", note="the non-causal trajectory"),
    )
    outputs = ()


@dataclasses.dataclass
class Collection:
    """What a run has received."""

    states: list = dataclasses.field(default_factory=list)
    stats: dict = dataclasses.field(default_factory=dict)  # service -> last ServiceStats
    window_p50: dict = dataclasses.field(default_factory=dict)  # (service, stage) -> [p50 per stats message]
    end: object | None = None
    last_state_time: float = 0.0
    arrivals: ArrivalLog = dataclasses.field(default_factory=ArrivalLog)  # frame and state arrival times
    extrinsics: np.ndarray | None = None  # (C,4,4) the newest refined T_SC (backend.refine_extrinsics), else None
    time_offset_s: float | None = None  # the newest camera-IMU time offset estimate (backend.estimate_time_offset)

    def __post_init__(self) -> None:
        from transport.pubsub import sample_sent_ns

        self.on_frame_arrival = self.arrivals.handler("frame", sent=sample_sent_ns)
        self.on_state_arrival = self.arrivals.handler("state", sent=sample_sent_ns)

    def on_window(self, msg) -> None:
        if len(msg.T_SC):
            self.extrinsics = np.array(msg.T_SC, float)
        if msg.status not in ("initialising", "reset"):
            self.time_offset_s = float(msg.time_offset_s)

    def add_stats(self, s) -> None:
        self.stats[s.service] = s
        for name, p50, n in zip(s.stage_names, s.stage_p50_ms, s.stage_count):
            if n > 0 and np.isfinite(p50):
                self.window_p50.setdefault((s.service, name), []).append(float(p50))


def subscribe(node: Node, col: Collection) -> dict:
    """A subscriber per declared input of :class:`RunCollectorNode`: with ``col``'s method of the input's handler
    name as its callback where it has one; returns the others by handler name (queues to drain)."""
    queues = {}
    for inp in RunCollectorNode.inputs:
        callback = getattr(col, inp.handler, None) if inp.handler.startswith("on_") else None
        sub = node.subscriber(inp.topic, policy=inp.policy, depth=inp.depth, handler=callback)
        if callback is None:
            queues[inp.handler] = sub
    return queues


def progress_line(col: Collection, elapsed_s: float) -> str:
    """What a run has received so far: states by status and how far into the sequence the last one is."""
    if not col.states:
        return f"{elapsed_s:.0f} s: no state yet (services starting, or the back end initialising)"
    status = [s.status for s in col.states]
    counts = ", ".join(f"{k} {status.count(k)}" for k in sorted(set(status)))
    span_s = (col.states[-1].header.stamp_ns - col.states[0].header.stamp_ns) * 1e-9
    return f"{elapsed_s:.0f} s: {len(col.states)} states ({counts}), {span_s:.1f} s into the sequence"


def collect(node: Node, col: Collection, queues: dict, sup_thread: threading.Thread, settle_s: float,
            timeout_s: float) -> str:
    """Collect until the player's stream has ended and its last frame's state is in (or no state came for
    ``settle_s`` after the end): 'done'; or 'services exited', 'timeout', 'stopped'."""
    states, stats, ends = queues["states"], queues["stats"], queues["ends"]
    t0 = next_report = time.monotonic()
    while not node.stopped:
        if time.monotonic() >= next_report:  # a line now and then, so a long run is never silent
            if next_report > t0:
                print(f"[sigmaslam run] {progress_line(col, time.monotonic() - t0)}", flush=True)
            next_report += PROGRESS_EVERY_S
        for s in stats.drain():
            col.add_stats(s)
        for e in ends.drain():
            if e.source == "player" and col.end is None:
                col.end = e
                col.last_state_time = max(col.last_state_time, time.monotonic())
                print(f"[sigmaslam run] player ended after {e.frames_sent} frames", flush=True)
        try:
            col.states.append(states.get(timeout=0.05))
            col.last_state_time = time.monotonic()
            col.states += states.drain()
        except Empty:
            pass
        now = time.monotonic()
        if col.end is not None:
            last = col.states[-1].header.stamp_ns if col.states else -1
            if last >= col.end.header.stamp_ns > 0 or now - col.last_state_time > settle_s:
                node.wait(1.5)  # one more stats period
                for s in stats.drain():
                    col.stats[s.service] = s
                return "done"
        if not sup_thread.is_alive():
            return "services exited"
        if timeout_s > 0 and now - t0 > timeout_s:
            return "timeout"
    return "stopped"


def wait_final(subscriber, timeout_s: float, stopped=lambda: False, report_every_s: float = 10.0):
    """The first FinalTrajectory on ``subscriber`` within ``timeout_s`` (None if none came); says every
    ``report_every_s`` that it is still waiting."""
    t0 = time.monotonic()
    t_end, next_report = t0 + timeout_s, t0 + report_every_s
    while time.monotonic() < t_end and not stopped():
        if time.monotonic() >= next_report:
            print(f"[sigmaslam run] still waiting for the final bundle adjustment ({time.monotonic() - t0:.0f} s)",
                  flush=True)
            next_report += report_every_s
        try:
            return subscriber.get(timeout=0.2)
        except Empty:
            continue
    return None
