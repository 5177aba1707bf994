"""Runs one transport-free process node (:class:`shared.dataflow.ProcessNode`) as a process over Zenoh.

::

    node = make_node(cfg, cameras)       # services/frontend/node.py: the frontend's node
    run_node(node, cfg.transport)        # until SIGTERM/SIGINT

(``sigmaslam <process>`` does this for every process from its description: services/app/process_cmd.py.)

The node's declared inputs become subscribers (their queue policy and depth), its outputs publishers. The loop
blocks on the trigger input; before each trigger message it drains the side inputs (first those the trigger waits
for, up to ``node.wait_s`` until one is stamped at or after the trigger, then the others in declared order), sheds
a backlog with the node's ``shed`` method when the trigger input declares one (else, on a keep-latest trigger
queue, keeps the newest ``depth`` messages taken but not yet handled, the rest counted as drops), tells the node how
many messages still wait behind the one it takes (``node.backlog``), and times the trigger's handler as
the node's stage in ``stats/<name>``, publishes what it returned, then calls the node's ``after_publish``; with ``node.trigger_period_s`` it takes trigger messages on a
schedule of that period (:func:`next_trigger_time`: a message that took longer than the period is made up by taking
the next one sooner, so the average rate holds; a keep-latest trigger queue drops the ones in between, counted). While no trigger message comes it drains the side inputs, hands the idle
inputs (end of stream) to the node and calls its ``tick``. What the handlers return is published in order. A node without a trigger
input handles every input as it arrives and ticks between (every ``POLL_S / 10``). At a stop, what the side and
idle inputs hold is handled before ``node.close()``.
"""

from __future__ import annotations

import logging
import time
from collections import deque

from shared.backlog import shed_backlog
from shared.dataflow import Emit, Input, ProcessNode, RejectedMessage
from shared.ratelimit import RateLimitedLog
from transport.config import TransportConfig
from transport.node import Node
from transport.queues import Empty

log = logging.getLogger(__name__)

POLL_S = 0.1  # how long the loop blocks on the trigger input before draining the others [s]


def next_trigger_time(scheduled: float, now: float, period_s: float) -> float:
    """When a paced node may take its next trigger message, having just taken one at ``now`` that was due at
    ``scheduled`` (monotonic seconds): one period after the due time, so that a slow message is made up by a sooner
    next one and the average rate stays 1 / ``period_s``; but the debt carried is at most half a period, so after a
    long stall (or idle) one message at most follows at once, not a burst."""
    return max(scheduled + period_s, now - 0.5 * period_s)


class _Wiring:
    """The node's subscribers and publishers on an open transport node."""

    def __init__(self, node: ProcessNode, tn: Node) -> None:
        self.node, self.tn = node, tn
        self.subs = {inp: tn.subscriber(inp.topic, policy=inp.policy, depth=inp.depth) for inp in node.inputs}
        for name, fn in node.counters().items():
            tn.stats.add_counter(name, fn)
        self.pubs = {t: tn.publisher(t) for t in node.outputs}
        for served in type(node).served:
            tn.queryable(served.question.key, served.question.request, getattr(node, served.handler))
        self.newest = {inp: -1 for inp in node.inputs}
        self.bad_log = RateLimitedLog(log)

    def publish(self, emits: list[Emit]) -> None:
        for e in emits:
            self.pubs[e.topic].publish(e.msg)

    def handle(self, inp: Input, msg) -> list[Emit]:
        """The node's handler; a message it rejects is counted as a drop of that input and logged (rate-limited)."""
        try:
            return self.node.handle(inp, msg)
        except RejectedMessage as exc:
            self.subs[inp].queue.count_drop()
            self.bad_log.warning("%s: %s dropped: %s", self.node.name, inp.topic.key, exc)
            return []

    def drain(self, inputs: list[Input]) -> None:
        for inp in inputs:
            for msg in self.subs[inp].drain():
                self.newest[inp] = max(self.newest[inp], int(msg.header.stamp_ns))
                self.publish(self.handle(inp, msg))


def run_node(node: ProcessNode, cfg: TransportConfig, stopped=None, ready=None) -> None:
    """Run ``node`` until the process is told to stop (or ``stopped()`` says so); then ``node.close()``.
    ``ready()`` is called once its subscribers and publishers exist (e.g. to print that the service runs)."""
    triggers = [i for i in node.inputs if i.role == "trigger"]
    if len(triggers) > 1:
        raise ValueError(f"{node.name}: more than one trigger input")
    trigger = triggers[0] if triggers else None
    waited = [i for i in node.inputs if i.role == "side" and i.wait_until_trigger_stamp]
    side = [i for i in node.inputs if i.role == "side" and not i.wait_until_trigger_stamp]
    idle = [i for i in node.inputs if i.role == "idle"]
    with Node(node.name, cfg, declared=node) as tn:
        node.timer_factory = lambda stage, budget_ms: tn.timer(stage, budget_ms=budget_ms)
        w = _Wiring(node, tn)
        timer = tn.timer(node.stage, budget_ms=node.budget_ms) if trigger is not None else None  # times the trigger
        if ready is not None:
            ready()
        done = (lambda: tn.stopped) if stopped is None else (lambda: tn.stopped or stopped())
        pending: deque = deque()
        next_t = time.monotonic()  # trigger pacing (node.trigger_period_s)
        while not done():
            if trigger is None:
                w.drain([*waited, *side, *idle])
                w.publish(node.tick())
                tn.wait(POLL_S / 10)
                continue
            sub = w.subs[trigger]
            if node.trigger_period_s > 0 and not pending and tn.wait(max(0.0, next_t - time.monotonic())):
                break
            if not pending:
                try:
                    pending.append(sub.get(timeout=POLL_S))
                except Empty:
                    w.drain([*waited, *side])
                    w.drain(idle)
                    w.publish(node.tick())
                    continue
            pending.extend(sub.drain())
            if trigger.shed is not None:
                kept, skipped = getattr(node, trigger.shed)(pending)
                if skipped:
                    sub.queue.count_shed(skipped)
                    log.warning("%s: %d messages behind, skipped %d to catch up", node.name, len(pending), skipped)
                pending = deque(kept)
            elif sub.queue.policy == "latest":  # keep-latest holds across turns, not only in the queue
                kept, skipped = shed_backlog(pending, sub.queue.maxlen, is_keyframe=lambda m: False)
                if skipped:
                    sub.queue.count_shed(skipped)
                    pending = deque(kept)
            msg = pending.popleft()
            node.backlog = len(pending)
            next_t = next_trigger_time(next_t, time.monotonic(), node.trigger_period_s)
            stamp = int(msg.header.stamp_ns)
            w.drain(waited)
            deadline = time.monotonic() + node.wait_s
            while (any(w.newest[i] < node.wait_stamp(i, stamp) for i in waited) and time.monotonic() < deadline
                   and not done()):
                time.sleep(0.002)
                w.drain(waited)
            w.drain(side)
            with timer:
                emits = w.handle(trigger, msg)
            w.publish(emits)
            w.publish(node.after_publish())
        w.drain([*waited, *side, *idle])  # what arrived before the stop is handled before the node closes
        w.publish(node.close())
