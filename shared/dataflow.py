"""Processes as transport-free nodes that declare their topics, and the in-process runner that drives them.

A process of sigmaslam is a :class:`ProcessNode`: it declares what it reads (:class:`Input`: a topic, the method
that handles each message, how its queue behaves) and what it writes (``outputs``: topics); each handler
returns the messages to publish as :class:`Emit` values, in order. Two runners drive the same nodes:

- ``transport.runner.run_node`` runs one node as a process over Zenoh (``sigmaslam frontend``, ...);
- :class:`InProcessRunner` (here) runs several nodes in one process, deterministically: every message, from the
  data source or emitted by a node, is delivered in stamp order (emitted messages before source messages of the
  same stamp, ties first-in first-out), which is what a lockstep player over Zenoh produces.

How a node's inputs are drained (``Input.role``) is part of the declaration, so both runners agree:

- ``"trigger"``: the input the process is paced by (camera frames, feature frames): each message is handled
  on its own, after the side inputs have been drained; its handler is timed as the node's stage;
- ``"side"``: drained (every message handled, in arrival order) before each trigger message; with
  ``wait_until_trigger_stamp`` the Zenoh runner first waits up to ``wait_s`` for a message stamped at or after
  the trigger's (IMU up to the frame's time; :meth:`ProcessNode.wait_stamp` may name an earlier stamp);
- ``"idle"``: handled only when no trigger message is pending (the end of a stream: after the last frame).

Queue behaviour (``policy``/``depth``: keep all or keep the newest N) and shedding (``shed``: the name of a
node method that, given the pending trigger messages, returns which to keep and how many it skipped) are
declared on the input too. :func:`graph` lists who publishes and who reads each topic (docs/architecture.md).
"""

from __future__ import annotations

import dataclasses
import heapq
import itertools
import logging
import time
from typing import Any, ClassVar, Iterable, Literal

from shared.codec import Message
from shared.ratelimit import RateLimitedLog
from shared.topics import Question, Topic


@dataclasses.dataclass(frozen=True)
class Input:
    """One declared input of a node."""

    topic: Topic
    handler: str  # name of the node's method called with each message
    role: Literal["trigger", "side", "idle"] = "side"
    policy: Literal["all", "latest"] | None = None  # queue policy (None: the topic's)
    depth: int | None = None  # queue depth (None: the topic's)
    wait_until_trigger_stamp: bool = False  # side input the trigger waits for (up to the node's wait_s)
    shed: str | None = None  # trigger input: node method (pending list) -> (kept list, skipped count)
    when: str = ""  # the condition under which the node reads it (docs), e.g. "o2p.enabled"; empty: always
    note: str = ""  # what the node uses it for (docs)


@dataclasses.dataclass(frozen=True)
class Served:
    """A question a node answers (:class:`shared.topics.Question`, a Zenoh queryable at ``<namespace>/<key>`` when
    run over Zenoh): each request goes to the node's method ``handler``, which returns the answer message or raises
    ValueError for a request it refuses (the asker gets the error's text). The handler runs on a thread of its own,
    beside the node's loop: it must only read what the loop writes, and tolerate reading it mid-change."""

    question: Question
    handler: str
    note: str = ""  # what it answers from (docs)


@dataclasses.dataclass(frozen=True)
class Emit:
    """A message a handler wants published on ``topic`` (one of the node's declared outputs)."""

    topic: Topic
    msg: Message


class StageClock:
    """A node's timer of one stage when no transport is there to report it: keeps each duration [s], wall and the
    running thread's CPU time."""

    def __init__(self, stage: str, budget_ms: float | None = None) -> None:
        self.stage, self.budget_ms, self.durations_s, self.cpu_s = stage, budget_ms, [], []

    def __enter__(self) -> "StageClock":
        self._t0, self._c0 = time.perf_counter(), time.thread_time()
        return self

    def __exit__(self, *exc) -> None:
        self.durations_s.append(time.perf_counter() - self._t0)
        self.cpu_s.append(time.thread_time() - self._c0)


class RejectedMessage(ValueError):
    """Raised by a handler for a message it cannot use: the runner counts it as a drop of that input (stats) and
    logs it (rate-limited); the node goes on."""


class UndeclaredTopic(ValueError):
    """A node published (or was wired to read) a topic it did not declare."""


class ProcessNode:
    """Base of the transport-free process nodes. Subclasses set the class attributes and write the handlers."""

    name: ClassVar[str]
    inputs: ClassVar[tuple[Input, ...]]
    outputs: ClassVar[tuple[Topic, ...]]
    output_notes: ClassVar[dict[str, str]] = {}  # topic key -> when / what is published (docs)
    served: ClassVar[tuple[Served, ...]] = ()  # questions it answers (queryables), see :class:`Served`
    stage: ClassVar[str] = "process"  # stage name of the trigger handler in stats/<name>
    budget_ms: float | None = None  # the stage's budget (per instance: from its config)
    wait_s: float = 0.0  # longest wait for a wait_until_trigger_stamp input [s] (per instance: from its config)
    trigger_period_s: float = 0.0  # handle a trigger message at most this often [s] (0: every one): the Zenoh
    # runner paces by wall time (newer messages replace older ones in a keep-latest queue), the in-process runner
    # by the messages' stamps (a trigger sooner than this after the last handled one is skipped)

    backlog: int = 0  # trigger messages already waiting when the one being handled was taken (set by the Zenoh
    # runner; always 0 in process, where nothing waits): a node may do less while it is behind

    def handle(self, inp: Input, msg: Message) -> list[Emit]:
        """Call ``inp``'s handler and check that everything it emits is a declared output."""
        out = getattr(self, inp.handler)(msg) or []
        for e in out:
            if e.topic not in self.outputs:
                raise UndeclaredTopic(f"{self.name}: emitted {e.topic.key!r}, not among its outputs "
                                      f"{[t.key for t in self.outputs]}")
        return out

    def wait_stamp(self, inp: Input, trigger_stamp_ns: int) -> int:
        """The stamp the ``wait_until_trigger_stamp`` input ``inp`` must have reached before the trigger message
        stamped ``trigger_stamp_ns`` is handled: by default the trigger's own; a node may ask for an earlier one
        (-1: do not wait)."""
        return trigger_stamp_ns

    def use_inputs(self, handlers: Iterable[str]) -> None:
        """Read only the declared inputs with these handlers (e.g. no loop-closure inputs when loop closure is
        off): the instance's ``inputs`` become that subset, in declared order; an undeclared handler is refused."""
        handlers = set(handlers)
        unknown = handlers - {i.handler for i in type(self).inputs}
        if unknown:
            raise UndeclaredTopic(f"{self.name}: no declared input has handler(s) {sorted(unknown)}")
        self.inputs = tuple(i for i in type(self).inputs if i.handler in handlers)

    def timer(self, stage: str, budget_ms: float | None = None):
        """Context manager timing a stage of the node's own work (beyond the trigger handler): reported in
        ``stats/<name>`` when run over Zenoh (the runner installs its timers), kept in a :class:`StageClock` else."""
        timers = self.__dict__.setdefault("_timers", {})
        if stage not in timers:
            factory = self.__dict__.get("timer_factory", StageClock)
            timers[stage] = factory(stage, budget_ms)
        return timers[stage]

    def counters(self) -> dict[str, Any]:
        """Counts for ``stats/<name>`` beside its queues (``counter_names``): name -> callable giving the count."""
        return {}

    def after_publish(self) -> list[Emit]:
        """Work a trigger message left for after its outputs are published (off the latency path), done before
        the next trigger message: called by both runners right after the trigger's handler; may emit."""
        return []

    def tick(self) -> list[Emit]:
        """Periodic work: called by the Zenoh runner while no trigger message is pending, by the in-process runner
        after each source message's messages; may emit."""
        return []

    def close(self) -> list[Emit]:
        """Called once when the runner stops (after the stream); may emit last messages."""
        return []


def graph(nodes: Iterable[type[ProcessNode]]) -> dict[str, dict[str, list[str]]]:
    """topic key -> {'publishers': [...], 'subscribers': [...]} over the given node classes."""
    out: dict[str, dict[str, list[str]]] = {}
    for n in nodes:
        for t in n.outputs:
            out.setdefault(t.key, {"publishers": [], "subscribers": []})["publishers"].append(n.name)
        for inp in n.inputs:
            out.setdefault(inp.topic.key, {"publishers": [], "subscribers": []})["subscribers"].append(n.name)
    return dict(sorted(out.items()))


class InProcessRunner:
    """Drives nodes in one process, deterministically, the way a lockstep run over Zenoh does.

    ``run(source)`` takes (topic, message) pairs in time order (a dataset's IMU and frames, then a StreamEnd) and
    hands each to every node that reads its topic; whatever the nodes emit is delivered in turn (stamp order, ties
    first-in first-out) until nothing is left, before the next source message: a frame is fully processed before
    the next is read, as with a player that waits for each state. A trigger message whose node waits for a side
    input (``wait_until_trigger_stamp``) that has not reached its stamp yet is held until that input does, or until
    nothing else is pending (the Zenoh runner's time-out). ``idle`` inputs are handled when nothing else is pending;
    every node's ``tick`` runs after each source message's messages. ``now_ns`` is the stamp of the latest source
    message (a sensor-time clock for nodes that need one). ``taps`` are called with every (topic, message)
    delivered (what a subscriber of everything sees)."""

    def __init__(self, nodes: list[ProcessNode], taps: Iterable[Any] = ()) -> None:
        self.nodes = nodes
        self.taps = list(taps)
        self.now_ns = 0
        self._heap: list = []
        self._idle: list = []
        self._held: list = []  # (stamp, seq, node, input, message): triggers waiting for a side input
        self._seq = itertools.count()
        self._last_trigger: dict[int, int] = {}
        self._newest: dict[tuple[int, int], int] = {}  # (id(node), id(input)) -> newest stamp handled
        self.emitted: dict[str, int] = {}
        self.rejected: dict[tuple[str, str], int] = {}  # (node name, topic key) -> messages its handler refused
        self._bad_log = RateLimitedLog(logging.getLogger(__name__))
        # (node name, handler) -> [(wall s, thread CPU s)] of every call: the per-stage times of an in-process run
        self.times: dict[tuple[str, str], list[tuple[float, float]]] = {}

    def _handle(self, node: ProcessNode, inp: Input, msg: Message) -> None:
        t0, c0 = time.perf_counter(), time.thread_time()
        try:
            out = node.handle(inp, msg)
        except RejectedMessage as exc:
            self.rejected[(node.name, inp.topic.key)] = self.rejected.get((node.name, inp.topic.key), 0) + 1
            self._bad_log.warning("%s: %s dropped: %s", node.name, inp.topic.key, exc)
            out = []
        self.times.setdefault((node.name, inp.handler), []).append((time.perf_counter() - t0, time.thread_time() - c0))
        key = (id(node), id(inp))
        self._newest[key] = max(self._newest.get(key, -1), int(msg.header.stamp_ns))
        self._emit(out)
        if inp.role == "trigger":
            t0, c0 = time.perf_counter(), time.thread_time()
            after = node.after_publish()
            if type(node).after_publish is not ProcessNode.after_publish:
                self.times.setdefault((node.name, "after_publish"), []).append(
                    (time.perf_counter() - t0, time.thread_time() - c0))
            self._emit(after)

    def _push(self, topic: Topic, msg: Message) -> None:
        heapq.heappush(self._heap, (int(msg.header.stamp_ns), next(self._seq), topic, msg))

    def _paced_out(self, node: ProcessNode, inp: Input, msg: Message) -> bool:
        """A trigger message that comes sooner than the node's trigger_period_s after the last one it handled."""
        if inp.role != "trigger" or node.trigger_period_s <= 0:
            return False
        stamp, last = int(msg.header.stamp_ns), self._last_trigger.get(id(node))
        if last is not None and stamp - last < node.trigger_period_s * 1e9 - 1e6:  # 1 ms slack for stamp jitter
            return True
        self._last_trigger[id(node)] = stamp
        return False

    def _waited_reached(self, node: ProcessNode, stamp: int) -> bool:
        return all(self._newest.get((id(node), id(i)), -1) >= node.wait_stamp(i, stamp)
                   for i in node.inputs if i.wait_until_trigger_stamp)

    def _release(self, node: ProcessNode | None = None) -> None:
        """Handle held triggers (of ``node`` whose waited inputs have caught up; with None, all: the time-out)."""
        self._held.sort(key=lambda h: (h[0], h[1]))
        keep = []
        for h in self._held:
            stamp, _, n, inp, msg = h
            if node is None or (n is node and self._waited_reached(n, stamp)):
                self._handle(n, inp, msg)
            else:
                keep.append(h)
        self._held = keep

    def _deliver(self, topic: Topic, msg: Message) -> None:
        for tap in self.taps:
            tap(topic, msg)
        for node in self.nodes:
            for inp in node.inputs:
                if inp.topic != topic or self._paced_out(node, inp, msg):
                    continue
                if inp.role == "idle":
                    self._idle.append((node, inp, msg))
                elif inp.role == "trigger" and not self._waited_reached(node, int(msg.header.stamp_ns)):
                    self._held.append((int(msg.header.stamp_ns), next(self._seq), node, inp, msg))
                else:
                    self._handle(node, inp, msg)
                    if inp.wait_until_trigger_stamp and self._held:
                        self._release(node)

    def _emit(self, emits: list[Emit]) -> None:
        for e in emits:
            self.emitted[e.topic.key] = self.emitted.get(e.topic.key, 0) + 1
            self._push(e.topic, e.msg)

    def _drain(self) -> None:
        while self._heap or self._held or self._idle:
            if self._heap:
                _, _, topic, msg = heapq.heappop(self._heap)
                self._deliver(topic, msg)
            elif self._held:  # nothing else will come before the next source message: stop waiting
                self._release()
            else:  # nothing else pending: the idle inputs' turn
                node, inp, msg = self._idle.pop(0)
                self._handle(node, inp, msg)

    def run(self, source: Iterable[tuple[Topic, Message]]) -> None:
        for topic, msg in source:
            self.now_ns = max(self.now_ns, int(msg.header.stamp_ns))
            self._push(topic, msg)
            self._drain()
            for node in self.nodes:
                self._emit(node.tick())
            self._drain()
        for node in self.nodes:
            self._emit(node.close())
        self._drain()
