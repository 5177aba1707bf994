"""Typed publishers and subscribers over Zenoh, with shared memory for large payloads.

Publishing: a message is encoded with :mod:`shared.codec`. Payloads of at least
``TransportConfig.shm_threshold_bytes`` go through Zenoh shared memory when
``TransportConfig.shared_memory`` is on: the message is encoded into a reusable scratch buffer and
copied once into a buffer of the process's SHM pool, which Zenoh hands to local subscribers by
reference. Smaller payloads (or a full pool, or none where the pool cannot be locked in memory) go as plain bytes.

Sequence numbers: messages are frozen, so a publisher never rewrites ``header.seq``; the caller sets
it, typically from :attr:`Publisher.next_seq` (the number of messages this publisher sent so far).

Subscribing: each sample is decoded in the Zenoh callback thread and either pushed into a
:class:`~transport.queues.BoundedQueue` (policy ``"latest"`` or ``"all"``) or passed to ``handler``.
A payload that does not decode as the expected type is counted as a drop and logged (rate-limited);
the subscriber keeps running. The zenoh Python binding exposes payloads (SHM or not) only through a
copy into ``bytes``; that single copy is the only one on the receive side: decoded arrays are
read-only views of it.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Callable

import zenoh

from shared import codec
from shared.codec import DecodeError, Message, MessageError
from shared.ratelimit import RateLimitedLog
from transport.config import TransportConfig
from transport.queues import BoundedQueue, Empty

log = logging.getLogger(__name__)

__all__ = ["Publisher", "Subscriber", "Empty", "shm_provider", "sample_sent_ns"]

_delivering = threading.local()  # the sample a subscriber's handler is being called with, per Zenoh thread


def sample_sent_ns() -> int | None:
    """In a subscriber's handler: when the publisher put the message, wall time [ns] of the publisher's clock
    (the sample's Zenoh timestamp; transport/session.py turns timestamping on), or None where the sample has none
    (a publisher without timestamping) or outside a handler."""
    return getattr(_delivering, "sent_ns", None)


def _sent_ns(sample: zenoh.Sample) -> int | None:
    ts = sample.timestamp
    return None if ts is None else int(ts.get_time_as_ntp64().as_nanos())

_shm_lock = threading.Lock()
_shm_providers: dict[int, object] = {}


def shm_provider(pool_bytes: int):
    """The process-wide Zenoh SHM provider with a pool of ``pool_bytes`` (created on first use), or None when the
    pool cannot be made here: Zenoh locks the pool in memory, and an unprivileged process may lock only
    RLIMIT_MEMLOCK (``ulimit -l``; often 8 MiB, and so in containers). Large payloads then go as plain bytes;
    one warning says why.

    Creating the pool and touching its pages the first time costs tens of ms, so the pool's pages are
    written once here, at publisher creation, instead of during the first publications.
    """
    from zenoh import shm

    with _shm_lock:
        if pool_bytes in _shm_providers:
            return _shm_providers[pool_bytes]
        try:
            provider = shm.ShmProvider.default_backend(pool_bytes)
        except zenoh.ZError as exc:
            provider = None
            log.warning("no shared memory in this process: a pool of %d MiB cannot be made (%s); the process may "
                        "lock %s in memory (ulimit -l). Large messages go as plain bytes", pool_bytes >> 20, exc,
                        _memlock_limit())
        else:
            _prefault(provider, pool_bytes)
        _shm_providers[pool_bytes] = provider
        return provider


def _memlock_limit() -> str:
    import resource

    soft = resource.getrlimit(resource.RLIMIT_MEMLOCK)[0]
    return "any amount" if soft == resource.RLIM_INFINITY else f"{soft >> 10} KiB"


def _prefault(provider, pool_bytes: int, block: int = 1 << 20) -> None:
    """Write every page of the pool once (allocate it block by block, then release it)."""
    held = []
    zeros = bytearray(block)
    try:
        for _ in range(pool_bytes // block):
            buf = provider.alloc(block)
            buf[0:block] = zeros
            held.append(buf)
    except zenoh.ZError:
        pass  # pool exhausted (alignment overhead): what was touched is enough
    del held
    provider.garbage_collect()


class Publisher:
    """Publishes messages of one type on one key expression.

    ``block=True`` makes Zenoh block instead of dropping when its transmission queue is full
    (use for topics that must not lose data, e.g. IMU). ``prepare_shm=True`` creates (and pre-faults)
    the process's SHM pool now rather than at the first large message (tens of ms, once per process);
    use it for topics with large payloads.
    """

    def __init__(self, session: zenoh.Session, key_expr: str, msg_type: type[Message],
                 cfg: TransportConfig | None = None, *, block: bool = False, express: bool = False,
                 prepare_shm: bool = True) -> None:
        self.cfg = cfg or TransportConfig()
        self.key_expr = key_expr
        self.msg_type = msg_type
        self._pub = session.declare_publisher(
            key_expr, congestion_control=zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP,
            express=express)
        self._scratch = bytearray()
        self._lock = threading.Lock()
        self.sent = 0
        self.sent_shm = 0
        self.shm_fallbacks = 0
        self.bytes_sent = 0
        self._shm_policy = None
        if self.cfg.shared_memory and prepare_shm:
            shm_provider(self.cfg.shm_pool_bytes)

    @property
    def next_seq(self) -> int:
        """Sequence number for the next message (messages sent so far)."""
        return self.sent

    def has_subscribers(self) -> bool:
        """Whether Zenoh knows of a subscriber matching this key expression (anywhere in the network)."""
        status = self._pub.matching_status
        return bool(getattr(status, "matching", status))

    def wait_for_subscribers(self, timeout: float = 5.0) -> bool:
        """Wait until :meth:`has_subscribers` (or ``timeout`` seconds); returns whether one appeared."""
        deadline = time.monotonic() + timeout
        while not self.has_subscribers():
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.01)
        return True

    def publish(self, msg: Message) -> int:
        """Encode and send ``msg``; returns the payload size in bytes. Raises MessageError on a wrong type."""
        if not isinstance(msg, self.msg_type):
            raise MessageError(f"publisher on {self.key_expr!r} sends {self.msg_type.__name__}, got {type(msg).__name__}")
        p = codec.plan(msg)
        with self._lock:
            if self.cfg.shared_memory and p.size >= self.cfg.shm_threshold_bytes and self._put_shm(p):
                self.sent_shm += 1
            else:
                buf = bytearray(p.size)
                codec.encode_into(p, buf)
                self._pub.put(buf)
            self.sent += 1
            self.bytes_sent += p.size
        return p.size

    def _put_shm(self, p: codec.EncodePlan) -> bool:
        from zenoh import shm

        if self._shm_policy is None:
            self._shm_policy = shm.GarbageCollect(shm.Defragment())
        provider = shm_provider(self.cfg.shm_pool_bytes)
        if provider is None:  # no pool in this process (said once, when it was tried)
            return False
        try:
            buf = provider.alloc(p.size, self._shm_policy)
        except zenoh.ZError as exc:
            self.shm_fallbacks += 1
            if self.shm_fallbacks == 1 or self.shm_fallbacks % 100 == 0:
                log.warning("%s: shared-memory pool full (%s), sending %d B as plain bytes (%d fallbacks so far)",
                            self.key_expr, exc, p.size, self.shm_fallbacks)
            return False
        if len(self._scratch) != p.size:
            self._scratch = bytearray(p.size)
        codec.encode_into(p, self._scratch)
        buf[0:p.size] = self._scratch
        self._pub.put(buf)
        return True

    def close(self) -> None:
        try:
            self._pub.undeclare()
        except zenoh.ZError:
            pass  # session already closed

    def __enter__(self) -> Publisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Subscriber:
    """Receives messages of one type (``msg_type=None``: any registered type) on a key expression.

    Queue mode (default): messages go into a bounded queue read with :meth:`get`, :meth:`get_nowait`,
    :meth:`drain`. Callback mode (``handler=``): ``handler(msg)`` runs in the Zenoh thread; an exception
    in it is logged (rate-limited) and counted in :attr:`handler_errors`, never propagated.
    ``on_drop(item, reason)`` is called for every dropped item (``item`` is the raw payload for
    undecodable ones, the message for queue overflow).
    """

    def __init__(self, session: zenoh.Session, key_expr: str, msg_type: type[Message] | None,
                 policy: str = "latest", depth: int = 4, on_drop: Callable[[object, str], None] | None = None,
                 handler: Callable[[Message], None] | None = None, name: str | None = None) -> None:
        self.key_expr = key_expr
        self.msg_type = msg_type
        self.name = name or key_expr
        self.queue: BoundedQueue[Message] = BoundedQueue(policy, depth, self.name, on_drop)
        self._on_drop = on_drop
        self._handler = handler
        self._bad_log = RateLimitedLog(log)
        self.received_shm = 0
        self.handler_errors = 0
        self._closed = False
        self._sub = session.declare_subscriber(key_expr, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        if self._closed:
            return
        try:
            self._deliver(sample)
        except Exception as exc:  # e.g. a failing on_drop callback: log, never break the subscription
            self._bad_log.warning("%s: error while delivering a sample: %s: %s", self.name, type(exc).__name__, exc)

    def _deliver(self, sample: zenoh.Sample) -> None:
        payload = sample.payload
        shm_buf = payload.as_shm()
        if shm_buf is not None:
            self.received_shm += 1
            data = bytes(shm_buf)
        else:
            data = payload.to_bytes()
        try:
            msg = codec.decode(data, self.msg_type)
        except DecodeError as exc:
            self.queue.count_drop()
            self._bad_log.warning("%s: dropped undecodable payload of %d B: %s", self.name, len(data), exc)
            if self._on_drop is not None:
                self._on_drop(data, f"undecodable: {exc}")
            return
        if self._handler is None:
            self.queue.put(msg)
            return
        self.queue.count_received()
        _delivering.sent_ns = _sent_ns(sample)
        try:
            self._handler(msg)
        except Exception as exc:  # a faulty handler must not kill the subscription
            self.handler_errors += 1
            self._bad_log.warning("%s: handler raised %s: %s", self.name, type(exc).__name__, exc)
        finally:
            _delivering.sent_ns = None

    # queue access
    def get(self, timeout: float | None = None) -> Message:
        return self.queue.get(timeout)

    def get_nowait(self) -> Message:
        return self.queue.get_nowait()

    def drain(self) -> list[Message]:
        return self.queue.drain()

    @property
    def received(self) -> int:
        return self.queue.received

    @property
    def dropped(self) -> int:
        return self.queue.dropped

    @property
    def depth(self) -> int:
        return self.queue.depth

    def counters(self) -> tuple[int, int, int]:
        """(received, dropped, depth)."""
        return self.queue.counters()

    def close(self) -> None:
        self._closed = True
        try:
            self._sub.undeclare()
        except zenoh.ZError:
            pass

    def __enter__(self) -> Subscriber:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
