"""Bounded queue policies, counters and blocking behaviour."""

import threading
import time

import pytest

from transport.queues import BoundedQueue, Empty


def test_latest_keeps_newest_and_counts_dropped_oldest():
    dropped = []
    q = BoundedQueue("latest", 3, "q", on_drop=lambda item, reason: dropped.append((item, reason)))
    for i in range(10):
        q.put(i)
    assert q.drain() == [7, 8, 9]
    assert (q.received, q.dropped, q.depth) == (10, 7, 0)
    assert [d[0] for d in dropped] == list(range(7))
    assert all("oldest" in d[1] for d in dropped)


def test_all_keeps_everything_up_to_bound_then_drops_newest():
    q = BoundedQueue("all", 5)
    results = [q.put(i) for i in range(8)]
    assert results == [True] * 5 + [False] * 3
    assert q.counters() == (8, 3, 5)
    assert [q.get_nowait() for _ in range(5)] == [0, 1, 2, 3, 4]
    with pytest.raises(Empty):
        q.get_nowait()
    q.put(99)  # room again after the consumer caught up
    assert q.get(timeout=0) == 99
    assert q.counters() == (9, 3, 0)


def test_get_waits_for_producer_and_times_out():
    q = BoundedQueue("latest", 2)
    t0 = time.monotonic()
    with pytest.raises(Empty):
        q.get(timeout=0.05)
    assert time.monotonic() - t0 >= 0.05
    threading.Timer(0.05, q.put, args=("x",)).start()
    assert q.get(timeout=2.0) == "x"


def test_concurrent_producers_lose_nothing_under_bound():
    q = BoundedQueue("all", 100_000)
    threads = [threading.Thread(target=lambda k=k: [q.put((k, i)) for i in range(2000)]) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    items = q.drain()
    assert len(items) == 8000 and q.dropped == 0
    for k in range(4):  # per-producer order preserved
        assert [i for kk, i in items if kk == k] == list(range(2000))


def test_count_drop_and_bad_arguments():
    q = BoundedQueue("all", 1)
    q.count_drop(2)
    assert q.counters() == (2, 2, 0)
    with pytest.raises(ValueError, match="policy"):
        BoundedQueue("newest", 1)
    with pytest.raises(ValueError, match="depth"):
        BoundedQueue("latest", 0)
