"""Thread-safe bounded queues with an explicit overflow policy and counters.

Two policies (the ``queue_policy`` of :class:`shared.topics.Topic`):

``"latest"``
    Keep the newest ``depth`` items; pushing onto a full queue drops the *oldest* item (counted).
    For images and depth: a slow consumer always works on the most recent data.
``"all"``
    Keep everything up to a hard bound of ``depth`` items; beyond it the *new* item is dropped
    (counted). For IMU samples, where a gap is worse than latency and order must be kept.

Counters: ``received`` (items pushed, dropped or not), ``dropped``, ``depth`` (items waiting now).
"""

from __future__ import annotations

import collections
import threading
import time
from typing import Callable, Generic, TypeVar

T = TypeVar("T")

POLICIES = ("latest", "all")


class Empty(Exception):
    """No item arrived before the timeout (or the queue is empty for ``get_nowait``)."""


class BoundedQueue(Generic[T]):
    """A bounded FIFO with a drop policy; ``put`` never blocks.

    ``on_drop(item, reason)`` is called (outside the lock) for each item dropped by the policy.
    """

    def __init__(self, policy: str = "latest", depth: int = 4, name: str = "",
                 on_drop: Callable[[T, str], None] | None = None) -> None:
        if policy not in POLICIES:
            raise ValueError(f"queue policy must be one of {POLICIES}, got {policy!r}")
        if not isinstance(depth, int) or depth < 1:
            raise ValueError(f"queue depth must be a positive int, got {depth!r}")
        self.policy = policy
        self.maxlen = depth
        self.name = name
        self._on_drop = on_drop
        self._items: collections.deque[T] = collections.deque()
        self._cond = threading.Condition(threading.Lock())
        self._received = 0
        self._dropped = 0

    # ------------------------------------------------------------------ producer side

    def put(self, item: T) -> bool:
        """Add an item; returns False when the policy dropped something (the oldest or this item)."""
        dropped: T | None = None
        did_drop = False
        with self._cond:
            self._received += 1
            if len(self._items) >= self.maxlen:
                did_drop = True
                self._dropped += 1
                if self.policy == "latest":
                    dropped = self._items.popleft()
                    self._items.append(item)
                else:
                    dropped = item
            else:
                self._items.append(item)
            self._cond.notify()
        if did_drop and self._on_drop is not None:
            reason = "queue full, dropped oldest" if self.policy == "latest" else "queue full, dropped newest"
            self._on_drop(dropped, reason)
        return not did_drop

    def count_drop(self, n: int = 1) -> None:
        """Count items that arrived but never made it into the queue (e.g. undecodable payloads)."""
        with self._cond:
            self._received += n
            self._dropped += n

    def count_shed(self, n: int = 1) -> None:
        """Count items the consumer took from the queue and discarded (e.g. skipped to catch up)."""
        with self._cond:
            self._dropped += n

    def count_received(self, n: int = 1) -> None:
        """Count items delivered elsewhere (a subscriber in callback mode bypasses the queue)."""
        with self._cond:
            self._received += n

    # ------------------------------------------------------------------ consumer side

    def get(self, timeout: float | None = None) -> T:
        """Oldest item; waits up to ``timeout`` seconds (forever if None), else raises :class:`Empty`."""
        with self._cond:
            if timeout is None:
                while not self._items:
                    self._cond.wait()
            else:
                deadline = time.monotonic() + timeout
                while not self._items:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        raise Empty(f"queue {self.name!r}: nothing within {timeout} s")
                    self._cond.wait(left)
            return self._items.popleft()

    def get_nowait(self) -> T:
        with self._cond:
            if not self._items:
                raise Empty(f"queue {self.name!r} is empty")
            return self._items.popleft()

    def drain(self) -> list[T]:
        """All waiting items, oldest first; the queue is empty afterwards."""
        with self._cond:
            items = list(self._items)
            self._items.clear()
            return items

    # ------------------------------------------------------------------ counters

    @property
    def received(self) -> int:
        return self._received

    @property
    def dropped(self) -> int:
        return self._dropped

    @property
    def depth(self) -> int:
        return len(self._items)

    def __len__(self) -> int:
        return len(self._items)

    def counters(self) -> tuple[int, int, int]:
        """(received, dropped, depth) read consistently."""
        with self._cond:
            return self._received, self._dropped, len(self._items)
