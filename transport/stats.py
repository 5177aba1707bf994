"""Per-stage timing against budgets, and the ServiceStats / Heartbeat messages built from it.

A :class:`StageTimer` measures one processing stage (``with timer: work()`` or
``timer.record(seconds)``); it keeps a sliding window of recent items for rate and percentiles and
counts items over budget since start. A :class:`StatsCollector` turns a service's timers and
subscription queues into one :class:`shared.messages.ServiceStats` message.

Per-item log (opt-in, for benchmarks): with ``$SIGMASLAM_STAGE_LOG`` naming a folder, every stage of every
service appends one record per item (:data:`STAGE_LOG_DTYPE`: wall time of the item's end [ns], duration [s],
CPU time of the timing thread over the item [s]: on a shared machine the steadier figure)
to ``<folder>/<service>.<stage>.bin``; :func:`read_stage_log` reads it back.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import os
import threading
import time
from typing import Callable

import numpy as np

from shared.messages import Header, Heartbeat, ServiceStats

STAGE_LOG_ENV = "SIGMASLAM_STAGE_LOG"
STAGE_LOG_DTYPE = np.dtype([("end_ns", "<i8"), ("seconds", "<f8"), ("cpu_seconds", "<f8")])


@dataclasses.dataclass(frozen=True)
class StageSnapshot:
    name: str
    count: int
    rate_hz: float
    p50_ms: float
    p99_ms: float
    budget_ms: float
    overruns: int


class StageTimer:
    """Times one stage. ``budget_ms=None``: no budget (never an overrun).

    The window holds the items of the last ``window_s`` seconds (at most ``max_items``).
    """

    def __init__(self, name: str, budget_ms: float | None = None, window_s: float = 10.0, max_items: int = 4096) -> None:
        if budget_ms is not None and not budget_ms > 0:
            raise ValueError(f"stage {name!r}: budget must be positive [ms], got {budget_ms!r}")
        self.name = name
        self.budget_ms = budget_ms
        self.window_s = window_s
        self._window: collections.deque[tuple[float, float]] = collections.deque(maxlen=max_items)
        self._lock = threading.Lock()
        self._local = threading.local()
        self.count = 0
        self.overruns = 0
        self._log_fd: int | None = None

    def log_to(self, path: str | os.PathLike) -> None:
        """Append one :data:`STAGE_LOG_DTYPE` record per item to ``path`` from now on."""
        self._log_fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)

    def __enter__(self) -> StageTimer:
        self._local.t0, self._local.c0 = time.perf_counter(), time.thread_time()
        return self

    def __exit__(self, *exc: object) -> None:
        self.record(time.perf_counter() - self._local.t0, time.thread_time() - self._local.c0)

    def record(self, seconds: float, cpu_seconds: float = math.nan) -> bool:
        """Record one item that took ``seconds`` (wall; ``cpu_seconds`` of the thread's CPU time, when known);
        returns True if it overran the budget (wall)."""
        over = self.budget_ms is not None and seconds * 1e3 > self.budget_ms
        with self._lock:
            self.count += 1
            self.overruns += over
            self._window.append((time.monotonic(), seconds))
        if self._log_fd is not None:
            try:
                os.write(self._log_fd, np.array([(time.time_ns(), seconds, cpu_seconds)], STAGE_LOG_DTYPE).tobytes())
            except OSError:
                self._log_fd = None  # a full disk must not stop the service
        return over

    def snapshot(self) -> StageSnapshot:
        now = time.monotonic()
        with self._lock:
            while self._window and now - self._window[0][0] > self.window_s:
                self._window.popleft()
            stamps = [t for t, _ in self._window]
            durations = np.array([d for _, d in self._window], dtype=float) * 1e3
            count, overruns = self.count, self.overruns
        rate = 0.0
        if len(stamps) >= 2 and stamps[-1] > stamps[0]:
            rate = (len(stamps) - 1) / (stamps[-1] - stamps[0])
        p50, p99 = (float(np.percentile(durations, 50)), float(np.percentile(durations, 99))) if len(durations) else (math.nan, math.nan)
        budget = math.nan if self.budget_ms is None else float(self.budget_ms)
        return StageSnapshot(self.name, count, rate, p50, p99, budget, overruns)


QueueCounters = Callable[[], tuple[int, int, int]]


def rss_mb() -> float:
    """Resident memory of this process [MiB]."""
    try:
        import psutil

        return psutil.Process(os.getpid()).memory_info().rss / 2**20
    except Exception:  # psutil missing or process info unavailable
        return math.nan


class StatsCollector:
    """Gathers stage timers, queue counters and other counts of one service into ServiceStats messages."""

    def __init__(self, service: str) -> None:
        self.service = service
        self.started = time.monotonic()
        self._stages: dict[str, StageTimer] = {}
        self._queues: dict[str, QueueCounters] = {}
        self._counters: dict[str, Callable[[], int]] = {}
        self._lock = threading.Lock()

    def add_stage(self, timer: StageTimer) -> StageTimer:
        with self._lock:
            if timer.name in self._stages and self._stages[timer.name] is not timer:
                raise ValueError(f"{self.service}: stage {timer.name!r} registered twice")
            self._stages[timer.name] = timer
        folder = os.environ.get(STAGE_LOG_ENV)
        if folder and timer._log_fd is None:
            try:
                os.makedirs(folder, exist_ok=True)
                timer.log_to(os.path.join(folder, f"{self.service}.{timer.name}.bin"))
            except OSError:
                pass  # logging is a benchmark aid only
        return timer

    def stage(self, name: str) -> StageTimer | None:
        return self._stages.get(name)

    def add_queue(self, name: str, counters: QueueCounters) -> None:
        """Register a queue by a function returning (received, dropped, depth), e.g. ``sub.counters``."""
        with self._lock:
            self._queues[name] = counters

    def add_counter(self, name: str, value: Callable[[], int]) -> None:
        """Register a count that is not a queue's (pixels dropped, points used, ...) by a function giving it."""
        with self._lock:
            self._counters[name] = value

    def collect(self, stamp_ns: int | None = None, seq: int = 0) -> ServiceStats:
        with self._lock:
            stages = [t.snapshot() for t in self._stages.values()]
            queues = [(name, fn()) for name, fn in self._queues.items()]
            counters = [(name, int(fn())) for name, fn in self._counters.items()]
        stamp_ns = time.time_ns() if stamp_ns is None else stamp_ns
        i64 = lambda xs: np.array(xs, dtype=np.int64)  # noqa: E731
        f64 = lambda xs: np.array(xs, dtype=np.float64)  # noqa: E731
        return ServiceStats(
            header=Header(stamp_ns=stamp_ns, seq=seq),
            service=self.service,
            uptime_s=time.monotonic() - self.started,
            rss_mb=rss_mb(),
            stage_names=tuple(s.name for s in stages),
            stage_count=i64([s.count for s in stages]),
            stage_rate_hz=f64([s.rate_hz for s in stages]),
            stage_p50_ms=f64([s.p50_ms for s in stages]),
            stage_p99_ms=f64([s.p99_ms for s in stages]),
            stage_budget_ms=f64([s.budget_ms for s in stages]),
            stage_overruns=i64([s.overruns for s in stages]),
            queue_names=tuple(name for name, _ in queues),
            queue_received=i64([c[0] for _, c in queues]),
            queue_dropped=i64([c[1] for _, c in queues]),
            queue_depth=i64([c[2] for _, c in queues]),
            counter_names=tuple(name for name, _ in counters),
            counter_values=i64([v for _, v in counters]),
        )


def read_stage_log(path: str | os.PathLike) -> np.ndarray:
    """Records of a per-item stage log (a partly written last record is ignored)."""
    data = open(path, "rb").read()
    n = len(data) // STAGE_LOG_DTYPE.itemsize
    return np.frombuffer(data[: n * STAGE_LOG_DTYPE.itemsize], STAGE_LOG_DTYPE)


def heartbeat(service: str, state: str = "running", stamp_ns: int | None = None, seq: int = 0) -> Heartbeat:
    """Heartbeat message of this process for ``service``."""
    if state not in ("starting", "running", "stopping"):
        raise ValueError(f"heartbeat state must be 'starting', 'running' or 'stopping', got {state!r}")
    return Heartbeat(header=Header(stamp_ns=time.time_ns() if stamp_ns is None else stamp_ns, seq=seq),
                     service=service, pid=os.getpid(), state=state)
