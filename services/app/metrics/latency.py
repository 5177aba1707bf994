"""Latency of a live run from arrival and send times: the wall time [ns] at which each message of a topic arrived at
one subscriber and, where the sample carries it, the time its publisher put it (its Zenoh timestamp,
transport.pubsub.sample_sent_ns), keyed by its header stamp.

- *As a consumer sees it* (arrival times): the first arrival of a sensor stamp on ``sensors/frame`` stands for the
  moment the player published it (one host, one clock), so latency(stamp) = arrival(topic, stamp) -
  arrival(sensors/frame, stamp). Right only for a subscriber that is never kept from its callbacks (the bench's
  probe, a process at the path to a pose's priority): a busy one sees frames late and reports too little.
- *As sent* (send times): latency(stamp) = sent(topic, stamp) - sent(sensors/frame, stamp), both from the
  publishers' clocks: what the pipeline took, whatever the subscriber's priority; without the delivery to a
  consumer, which the difference of the two measures.

- :class:`ArrivalLog`: (stamp, arrival) per topic name, filled by subscriber callbacks;
- :func:`matched_latencies`: latency per stamp of a topic whose messages carry the sensor stamp
  (estimator/state, depth/fused);
- :func:`map_latencies`: sensor stamp -> first ``map/submap`` message that arrived after that stamp's depth frame
  (submap meshes carry the submap's anchor stamp, not the frame's; the mapper publishes changed submaps every
  ``mapping.mesh_period_s``, so this includes that period). A lower bound when the mapper runs behind its input;
- :func:`summary`: n, mean, median, p90, p99, max of a sample.

Used by ``sigmaslam run`` (pose latency of every run) and ``python -m tools bench pipeline``.
"""

from __future__ import annotations

import threading
import time

import numpy as np


def summary(values, unit_scale: float = 1.0) -> dict:
    """n, mean, median, p90, p99, max of ``values * unit_scale`` (NaN-free; empty -> n=0 only)."""
    v = np.asarray(values, float).ravel() * unit_scale
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return {"n": 0}
    return {"n": int(len(v)), "mean": float(v.mean()), "median": float(np.median(v)),
            "p90": float(np.percentile(v, 90)), "p99": float(np.percentile(v, 99)), "max": float(v.max())}


NO_TIME = -1  # a message without a send time


class ArrivalLog:
    """Thread-safe record of (header stamp, arrival wall time, send wall time or NO_TIME) per topic name."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._data: dict[str, list[tuple[int, int, int]]] = {}

    def handler(self, name: str, clock=time.time_ns, sent=lambda: None):
        """A subscriber callback that logs each message's header stamp under ``name`` with its arrival time
        (``clock()``) and send time (``sent()`` in the callback: transport.pubsub.sample_sent_ns; None: unknown)."""
        rows = self._data.setdefault(name, [])

        def on_msg(msg) -> None:
            t, t_sent = clock(), sent()
            with self._lock:
                rows.append((int(msg.header.stamp_ns), t, NO_TIME if t_sent is None else int(t_sent)))
        return on_msg

    def add(self, name: str, stamp_ns: int, arrival_ns: int, sent_ns: int = NO_TIME) -> None:
        with self._lock:
            self._data.setdefault(name, []).append((int(stamp_ns), int(arrival_ns), int(sent_ns)))

    def _rows(self, name: str) -> np.ndarray:
        with self._lock:
            rows = list(self._data.get(name, []))
        return np.array(rows, np.int64).reshape(-1, 3)

    def get(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(stamps_ns, arrivals_ns) in arrival order."""
        a = self._rows(name)
        return a[:, 0], a[:, 1]

    def sent_column(self, name: str) -> np.ndarray:
        """The send times (NO_TIME where unknown) in the order of :meth:`get`."""
        return self._rows(name)[:, 2]

    def get_sent(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(stamps_ns, sent_ns) in arrival order, of the messages that carried a send time."""
        a = self._rows(name)
        a = a[a[:, 2] != NO_TIME]
        return a[:, 0], a[:, 2]


def sent_latencies(log: ArrivalLog, name: str) -> dict:
    """:func:`matched_latencies` of topic ``name`` from send times: sent(name) - sent(sensors/frame) per stamp."""
    return matched_latencies(first_arrivals(*log.get_sent("frame")), *log.get_sent(name))


def sensor_clock_latencies(log: ArrivalLog, name: str) -> dict:
    """:func:`matched_latencies` of topic ``name`` from the sensor's clock: its put minus the frame's stamp carried to
    the publisher's wall clock by the smallest (put - stamp) of any frame, so that a source that publishes a frame
    late (a busy player or driver) counts against the latency, which the figure from send times does not see."""
    stamps, sent = log.get_sent("frame")
    offset = int(np.min(sent - stamps)) if len(stamps) else 0
    return matched_latencies({s: s + offset for s in stamps.tolist()}, *log.get_sent(name))


def first_arrivals(stamps_ns: np.ndarray, arrivals_ns: np.ndarray) -> dict[int, int]:
    """Earliest arrival per stamp."""
    out: dict[int, int] = {}
    for s, t in zip(stamps_ns.tolist(), arrivals_ns.tolist()):
        if s not in out or t < out[s]:
            out[s] = t
    return out


def matched_latencies(published: dict[int, int], stamps_ns: np.ndarray, arrivals_ns: np.ndarray) -> dict:
    """Per message whose stamp was published: ``stamp_ns``, ``arrival_ns`` and ``latency_ms``; ``unmatched`` counts
    the messages whose stamp the bench never saw published (e.g. published before it subscribed)."""
    keep = np.array([s in published for s in stamps_ns.tolist()], bool)
    s, a = stamps_ns[keep], arrivals_ns[keep]
    pub = np.array([published[x] for x in s.tolist()], np.int64)
    return {"stamp_ns": s, "arrival_ns": a, "latency_ms": (a - pub) / 1e6, "unmatched": int((~keep).sum())}


def map_latencies(published: dict[int, int], depth_stamps_ns: np.ndarray, depth_arrivals_ns: np.ndarray,
                  submap_arrivals_ns: np.ndarray) -> dict:
    """Sensor stamp -> the first submap message after the stamp's depth frame arrived (see the module doc)."""
    first_depth = first_arrivals(depth_stamps_ns, depth_arrivals_ns)
    sub = np.sort(np.asarray(submap_arrivals_ns, np.int64))
    stamps, arrivals = [], []
    for s, t in sorted(first_depth.items()):
        if s not in published:
            continue
        k = np.searchsorted(sub, t, side="left")
        if k < len(sub):
            stamps.append(s)
            arrivals.append(sub[k])
    s, a = np.array(stamps, np.int64), np.array(arrivals, np.int64)
    pub = np.array([published[x] for x in s.tolist()], np.int64)
    return {"stamp_ns": s, "arrival_ns": a, "latency_ms": (a - pub) / 1e6, "unmatched": 0}
