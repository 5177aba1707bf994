"""What ``sigmaslam bench pipeline`` measures beside the services' own stats, without touching them.

- :class:`ArrivalLog`: the wall time [ns] at which each message of a topic arrived here, keyed by its header
  stamp. The bench subscribes to ``sensors/frame`` itself: the first arrival of a sensor stamp stands for the
  moment the player published it (one host, one clock; the ~1 ms transport to the bench is included in neither
  end nor subtracted), so latency(stamp) = arrival(topic, stamp) - arrival(sensors/frame, stamp).
- :func:`matched_latencies`: latency per stamp of a topic whose messages carry the sensor stamp
  (estimator/state, depth/fused).
- :func:`map_latencies`: sensor stamp -> first ``map/submap`` message that arrived after that stamp's
  ``depth/fused`` (submap meshes carry the submap's anchor stamp, not the frame's; the mapper publishes
  changed submaps every ``mapping.mesh_period_s``, so this includes that period). A lower bound when the
  mapper runs behind its input.
- :class:`ProcessSampler`: CPU share and resident memory of each child process of this one (the services the
  supervisor started), named by their ``services.app.cli <subcommand>`` argument.
- :func:`summary` / :func:`stage_summary`: median, p90, p99 of a sample.
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


class ArrivalLog:
    """Thread-safe record of (header stamp, arrival wall time) per topic name."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._data: dict[str, list[tuple[int, int]]] = {}

    def handler(self, name: str, clock=time.time_ns):
        """A subscriber callback that logs each message's header stamp under ``name``."""
        rows = self._data.setdefault(name, [])

        def on_msg(msg) -> None:
            t = clock()
            with self._lock:
                rows.append((int(msg.header.stamp_ns), t))
        return on_msg

    def add(self, name: str, stamp_ns: int, arrival_ns: int) -> None:
        with self._lock:
            self._data.setdefault(name, []).append((int(stamp_ns), int(arrival_ns)))

    def get(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(stamps_ns, arrivals_ns) in arrival order."""
        with self._lock:
            rows = list(self._data.get(name, []))
        if not rows:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        a = np.array(rows, np.int64)
        return a[:, 0], a[:, 1]


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


def service_name(cmdline: list[str]) -> str | None:
    """'frontend' for ``python -m services.app.cli frontend CONFIG ...``; None for other processes."""
    for i, arg in enumerate(cmdline[:-1]):
        if arg == "services.app.cli":
            return cmdline[i + 1]
    return None


class ProcessSampler:
    """Samples CPU [% of one core] and RSS [MiB] of this process's descendants every ``period_s`` (a thread)."""

    def __init__(self, period_s: float = 0.5) -> None:
        import psutil

        self._psutil = psutil
        self.period_s = period_s
        self.samples: dict[str, list[tuple[float, float, float]]] = {}  # name -> (t_s, cpu_pct, rss_mb)
        self.cpu_time_s: dict[str, float] = {}  # name -> user+system CPU seconds at the last sample
        self._procs: dict[int, object] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="process-sampler", daemon=True)
        self.t0 = time.monotonic()

    def start(self) -> ProcessSampler:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)

    def _loop(self) -> None:
        me = self._psutil.Process()
        while not self._stop.wait(self.period_s):
            try:
                children = me.children(recursive=True)
            except self._psutil.Error:
                continue
            for p in children:
                p = self._procs.get(p.pid, p)  # the same object: cpu_percent() measures since its last call
                if p.pid not in self._procs:
                    self._procs[p.pid] = p
                    try:
                        p.cpu_percent(None)  # primes the counter; the next call gives the share since now
                    except self._psutil.Error:
                        pass
                    continue
                try:
                    name = service_name(p.cmdline())
                    if name is None:
                        continue
                    cpu = p.cpu_percent(None)
                    rss = p.memory_info().rss / 2**20
                    ct = p.cpu_times()
                except self._psutil.Error:
                    continue
                self.samples.setdefault(name, []).append((time.monotonic() - self.t0, cpu, rss))
                self.cpu_time_s[name] = ct.user + ct.system

    def summary(self) -> dict:
        """Per service: mean and p90 CPU [% of one core], share of the machine, median and peak RSS [MiB]."""
        ncpu = self._psutil.cpu_count() or 1
        out = {}
        for name, rows in sorted(self.samples.items()):
            a = np.array(rows, float)
            out[name] = {"cpu_mean_pct": float(a[:, 1].mean()), "cpu_p90_pct": float(np.percentile(a[:, 1], 90)),
                         "machine_share": float(a[:, 1].mean() / (100.0 * ncpu)),
                         "rss_median_mb": float(np.median(a[:, 2])), "rss_peak_mb": float(a[:, 2].max()),
                         "cpu_time_s": float(self.cpu_time_s.get(name, float("nan"))), "samples": len(rows)}
        return out

    def series(self) -> dict[str, np.ndarray]:
        return {k: np.array(v, float) for k, v in self.samples.items()}
