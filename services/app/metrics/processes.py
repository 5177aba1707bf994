"""What a measured run (``run_pipeline(..., measure=True)``: the eval suite's live figures, the pipeline bench)
samples of its processes beside their own stats, without touching them (arrival times and latencies:
services/app/metrics/latency.py).

- :class:`ProcessSampler`: CPU share and resident memory of each child process of this one (the services the
  supervisor started), named by their ``services.app.cli <subcommand>`` argument, and how long each one's main
  thread ran and how long it was ready to run but waited for a core (Linux ``/proc/<pid>/schedstat``): on a
  machine with fewer cores than busy services, the wait is where a stage's wall time goes beyond its CPU time.
"""

from __future__ import annotations

import threading
import time

import numpy as np


def service_name(cmdline: list[str]) -> str | None:
    """'frontend' for ``python -m services.app.cli frontend CONFIG ...``; None for other processes."""
    for i, arg in enumerate(cmdline[:-1]):
        if arg == "services.app.cli":
            return cmdline[i + 1]
    return None


def main_thread_schedstat(pid: int) -> tuple[int, int] | None:
    """(time on a CPU, time ready to run but waiting for a CPU) of process ``pid``'s main thread so far [ns], from
    ``/proc/<pid>/schedstat``; None where the kernel does not provide it (not Linux, schedstats off, gone)."""
    try:
        with open(f"/proc/{pid}/schedstat") as f:
            fields = f.read().split()
        return int(fields[0]), int(fields[1])
    except (OSError, ValueError, IndexError):
        return None


class ProcessSampler:
    """Samples CPU [% of one core] and RSS [MiB] of this process's descendants every ``period_s`` (a thread)."""

    def __init__(self, period_s: float = 0.5) -> None:
        import psutil

        self._psutil = psutil
        self.period_s = period_s
        self.samples: dict[str, list[tuple[float, float, float]]] = {}  # name -> (t_s, cpu_pct, rss_mb)
        self.cpu_time_s: dict[str, float] = {}  # name -> user+system CPU seconds at the last sample
        # name -> pid -> [(t_s, run_ns, wait_ns) of its first sample, the same of its last] of the main thread (a
        # restarted service is a new pid whose counters start again from 0)
        self.schedstat: dict[str, dict[int, list[tuple[float, int, int]]]] = {}
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
                t = time.monotonic() - self.t0
                self.samples.setdefault(name, []).append((t, cpu, rss))
                self.cpu_time_s[name] = ct.user + ct.system
                sched = main_thread_schedstat(p.pid)
                if sched is not None:
                    ends = self.schedstat.setdefault(name, {}).setdefault(p.pid, [(t, *sched)])
                    ends[1:] = [(t, *sched)]

    def summary(self) -> dict:
        """Per service: mean and p90 CPU [% of one core], share of the machine, median and peak RSS [MiB], and the
        main thread's time on a CPU and waiting for one [% of the wall time between its first and last sample;
        NaN without schedstat]."""
        ncpu = self._psutil.cpu_count() or 1
        out = {}
        for name, rows in sorted(self.samples.items()):
            a = np.array(rows, float)
            out[name] = {"cpu_mean_pct": float(a[:, 1].mean()), "cpu_p90_pct": float(np.percentile(a[:, 1], 90)),
                         "machine_share": float(a[:, 1].mean() / (100.0 * ncpu)),
                         "rss_median_mb": float(np.median(a[:, 2])), "rss_peak_mb": float(a[:, 2].max()),
                         "cpu_time_s": float(self.cpu_time_s.get(name, float("nan"))), "samples": len(rows),
                         **main_thread_shares(list(self.schedstat.get(name, {}).values()))}
        return out

    def series(self) -> dict[str, np.ndarray]:
        return {k: np.array(v, float) for k, v in self.samples.items()}


def main_thread_shares(lives: list[list[tuple[float, int, int]]]) -> dict[str, float]:
    """'main_thread_run_pct' and 'main_thread_wait_pct' from the first and last (t_s, run_ns, wait_ns) sample of
    each life of a service (one per pid): the share of the wall time from its first sample to its last that the
    main thread ran, and that it was ready but waited [%]; NaN without two samples."""
    spans = [(e[0], e[-1]) for e in lives if len(e) >= 2]
    t0 = min((a[0] for a, _ in spans), default=0.0)
    t1 = max((b[0] for _, b in spans), default=0.0)
    if t1 <= t0:
        return {"main_thread_run_pct": float("nan"), "main_thread_wait_pct": float("nan")}
    wall_ns = (t1 - t0) * 1e9
    run = sum(b[1] - a[1] for a, b in spans)
    wait = sum(b[2] - a[2] for a, b in spans)
    return {"main_thread_run_pct": 100.0 * run / wall_ns, "main_thread_wait_pct": 100.0 * wait / wall_ns}
