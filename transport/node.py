"""The thin shell every sigmaslam service runs in.

::

    with Node("frontend", cfg.transport) as node:
        frames = node.subscriber(topics.FRAME)
        out = node.publisher(topics.FEATURES)
        track = node.timer("track", budget_ms=20.0)
        while not node.stopped:
            try:
                frame = frames.get(timeout=0.1)
            except Empty:
                continue
            with track:
                result = tracker.process(frame)
            out.publish(result)

The node opens the Zenoh session, creates typed publishers/subscribers for :mod:`shared.topics`
topics under the configured namespace, publishes ``heartbeat/<name>`` and ``stats/<name>``
periodically from a background thread, turns SIGTERM/SIGINT into :attr:`Node.stop_event` (a second
signal raises KeyboardInterrupt), and closes everything on exit. Loops must wait with timeouts
(``get(timeout=...)``, ``node.wait(seconds)``) so that they notice the stop promptly.
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from typing import Callable

import zenoh

from shared import messages, topics
from shared.codec import Message
from shared.topics import Topic
from transport.config import TransportConfig
from transport.pubsub import Publisher, Subscriber
from transport.session import open_session
from transport.stats import StageTimer, StatsCollector, heartbeat

log = logging.getLogger(__name__)

# message types whose payloads usually exceed the SHM threshold: their publishers prepare the SHM pool
LARGE_TYPES = (messages.MultiCameraFrame, messages.DepthFrame, messages.SubmapMesh)


class Node:
    """Session, publishers, subscribers, timers and periodic stats/heartbeat of one service."""

    def __init__(self, name: str, cfg: TransportConfig | None = None, *, handle_signals: bool = True,
                 declared=None) -> None:
        if not name or "/" in name or "*" in name:
            raise ValueError(f"service name must be non-empty without '/' or '*', got {name!r}")
        self.name = name
        self.cfg = cfg or TransportConfig()
        self.stop_event = threading.Event()
        self.stats = StatsCollector(name)
        self.session: zenoh.Session | None = None
        self._handle_signals = handle_signals
        self._old_handlers: dict[int, object] = {}
        self._signals_seen = 0
        self._publishers: list[Publisher] = []
        self._subscribers: list[Subscriber] = []
        self._servers: list = []  # transport.queryable.QueryServer of each question the node answers
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None
        self._state = "starting"
        # the process's declaration (shared.dataflow.ProcessNode class or instance): subscribing or publishing a
        # topic it does not declare is refused (stats/ and heartbeat/ belong to every node)
        self.declared = declared

    # ------------------------------------------------------------------ lifecycle

    def open(self) -> Node:
        self.session = open_session(self.cfg)
        try:
            self._stats_pub = self.publisher(topics.STATS, key=topics.per_service(topics.STATS, self.name))
            self._hb_pub = self.publisher(topics.HEARTBEAT, key=topics.per_service(topics.HEARTBEAT, self.name))
            self._publish_heartbeat()
            if self._handle_signals and threading.current_thread() is threading.main_thread():
                for sig in (signal.SIGTERM, signal.SIGINT):
                    self._old_handlers[sig] = signal.signal(sig, self._on_signal)
            self._state = "running"
            self._thread = threading.Thread(target=self._periodic, name=f"{self.name}-stats", daemon=True)
            self._thread.start()
        except BaseException:
            self.close()
            raise
        log.info("%s: joined %s as %s (namespace %s)", self.name, self.cfg.connect, self.cfg.mode, self.cfg.namespace)
        return self

    def close(self) -> None:
        """Publish a 'stopping' heartbeat and close everything; safe to call twice."""
        self.stop_event.set()
        self._closing.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        for sig, old in self._old_handlers.items():
            signal.signal(sig, old)
        self._old_handlers.clear()
        if self.session is None:
            return
        try:
            if self._state != "stopping" and hasattr(self, "_hb_pub"):
                self._state = "stopping"
                self._publish_heartbeat()
        finally:
            for server in self._servers:
                server.close()
            self._servers.clear()
            for sub in self._subscribers:
                sub.close()
            for pub in self._publishers:
                pub.close()
            self._subscribers.clear()
            self._publishers.clear()
            session, self.session = self.session, None
            session.close()

    def __enter__(self) -> Node:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def stopped(self) -> bool:
        return self.stop_event.is_set()

    def stop(self) -> None:
        self.stop_event.set()

    def wait(self, seconds: float) -> bool:
        """Sleep up to ``seconds``, waking early on stop; returns True if stopped."""
        return self.stop_event.wait(seconds)

    def _on_signal(self, signum: int, _frame: object) -> None:
        self._signals_seen += 1
        if self._signals_seen > 1:
            raise KeyboardInterrupt(f"second signal {signal.Signals(signum).name}")
        log.info("%s: %s received, stopping", self.name, signal.Signals(signum).name)
        self.stop_event.set()

    # ------------------------------------------------------------------ endpoints

    def key_expr(self, topic: Topic | str, key: str | None = None) -> str:
        rel = key if key is not None else (topic.key if isinstance(topic, Topic) else topic)
        return f"{self.cfg.namespace.rstrip('/')}/{rel}"

    def publisher(self, topic: Topic, *, key: str | None = None, block: bool | None = None) -> Publisher:
        """Publisher of ``topic.msg_type`` on ``<namespace>/<key or topic.key>``; topics with policy
        'all' block instead of dropping when Zenoh's queue is full (unless ``block`` says otherwise)."""
        self._require_open()
        self._check_declared(topic, "outputs")
        if key is None and "*" in topic.key:
            raise ValueError(f"topic {topic.key!r} is per-service: pass key=topics.per_service(topic, name)")
        block = topic.queue_policy == "all" if block is None else block
        pub = Publisher(self.session, self.key_expr(topic, key), topic.msg_type, self.cfg, block=block,
                        prepare_shm=topic.msg_type in LARGE_TYPES)
        self._publishers.append(pub)
        return pub

    def subscriber(self, topic: Topic, *, key: str | None = None, policy: str | None = None, depth: int | None = None,
                   handler: Callable[[Message], None] | None = None,
                   on_drop: Callable[[object, str], None] | None = None) -> Subscriber:
        """Subscriber to ``topic`` (queue policy and depth from the topic unless given); its counters
        appear in this node's stats under the relative key."""
        self._require_open()
        self._check_declared(topic, "inputs")
        rel = key if key is not None else topic.key
        sub = Subscriber(self.session, self.key_expr(topic, key), topic.msg_type,
                         policy or topic.queue_policy, depth or topic.queue_depth,
                         on_drop=on_drop, handler=handler, name=rel)
        self._subscribers.append(sub)
        self.stats.add_queue(rel, sub.counters)
        return sub

    def queryable(self, key: str, request: type[Message], handler: Callable[[Message], Message]):
        """Answer requests of type ``request`` at ``<namespace>/<key>`` with ``handler`` on a thread of their own
        (transport/queryable.py); the answered and refused counts appear in this node's stats."""
        from transport.queryable import QueryServer

        self._require_open()
        server = QueryServer(self.session, self.key_expr(key), request, handler, name=key)
        self._servers.append(server)
        for what in ("answered", "refused", "failed"):
            self.stats.add_counter(f"{key}_{what}", lambda s=server, w=what: getattr(s, w))
        return server

    def timer(self, stage: str, budget_ms: float | None = None) -> StageTimer:
        """Stage timer reported in this node's stats (the same one if asked twice)."""
        existing = self.stats.stage(stage)
        if existing is not None:
            return existing
        return self.stats.add_stage(StageTimer(stage, budget_ms))

    def _check_declared(self, topic: Topic, side: str) -> None:
        if self.declared is None or topic in (topics.STATS, topics.HEARTBEAT):
            return
        from shared.dataflow import UndeclaredTopic

        cls = self.declared if isinstance(self.declared, type) else type(self.declared)
        declared = cls.outputs if side == "outputs" else [i.topic for i in cls.inputs]
        if topic not in declared:
            raise UndeclaredTopic(f"{self.name}: {'publishes' if side == 'outputs' else 'subscribes to'} "
                                  f"{topic.key!r}, which its declaration does not list in its {side}")

    def _require_open(self) -> None:
        if self.session is None:
            raise RuntimeError(f"node {self.name!r} is not open (use 'with Node(...) as node:')")

    # ------------------------------------------------------------------ periodic output

    def _publish_heartbeat(self) -> None:
        self._hb_pub.publish(heartbeat(self.name, self._state, seq=self._hb_pub.next_seq))

    def publish_stats(self) -> None:
        self._stats_pub.publish(self.stats.collect(seq=self._stats_pub.next_seq))

    def _periodic(self) -> None:
        hb_period = max(self.cfg.heartbeat_period_s, 0.01)
        st_period = max(self.cfg.stats_period_s, 0.01)
        now = time.monotonic()
        next_hb, next_st = now + hb_period, now + st_period
        while not self._closing.wait(max(0.0, min(next_hb, next_st) - time.monotonic())):
            now = time.monotonic()
            try:
                if now >= next_hb:
                    next_hb = now + hb_period
                    self._publish_heartbeat()
                if now >= next_st:
                    next_st = now + st_period
                    self.publish_stats()
            except Exception as exc:  # a failed publish must not end the stats thread
                log.warning("%s: periodic stats/heartbeat failed: %s", self.name, exc)
