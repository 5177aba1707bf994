"""The pipeline bench's subscriber, a process of its own: when each frame, state, set of tracks, depth frame and submap
arrived (wall time, per header stamp), for the latencies of tools/bench_pipeline.py.

It runs where a consumer of poses would: a program of its own, at the priority of the path to a pose
(services/app/scheduling.py: real-time at ``supervisor.realtime_priority`` as the frontend and the player, else nice
-10 in a scheduling group of its own, where allowed). In the bench's process it shared the group of depth and
mapping, and on one busy core it saw frames seconds late: latencies below zero; at nice -10 beside a real-time
frontend and player it took frames and states together on one core (2026-12-08).

``python -m tools.bench_probe --config C --set K=V ... --out arrivals.npz`` prints ``ready`` once subscribed and
writes ``arrivals.npz`` (``<name>_stamp_ns``, ``<name>_arrival_ns`` and ``<name>_sent_ns``, the publisher's send time
or -1, per topic name) when it gets SIGTERM.
:class:`Probe` starts and reads it.
"""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np

from services.app.metrics.latency import NO_TIME, ArrivalLog

NAMES = ("frame", "state", "features", "depth", "map")


class Probe:
    """``with Probe(config, sets, out_npz) as probe:`` the subscriber process runs; ``probe.log`` holds its arrivals
    once the block has ended."""

    def __init__(self, config: str | None, sets: list[str], out_npz: Path, ready_timeout_s: float = 60.0) -> None:
        self.argv = [sys.executable, "-m", "tools.bench_probe", "--out", str(out_npz),
                     *(["--config", config] if config else []), *(a for s in sets for a in ("--set", s))]
        self.out_npz, self.ready_timeout_s = Path(out_npz), ready_timeout_s
        self.config, self.sets = config, list(sets)
        self.log = ArrivalLog()
        self.proc: subprocess.Popen | None = None

    def __enter__(self) -> "Probe":
        from services.app.scheduling import apply_in_child, resolve_scheduling
        from services.app.system_config import load_system_config

        priority = load_system_config(self.config, self.sets).supervisor.realtime_priority
        nice, sched, rt, why = resolve_scheduling(-10, "fifo", priority)
        if why:
            print(f"[bench pipeline] probe: {why}", flush=True)
        self.out_npz.unlink(missing_ok=True)
        self.proc = subprocess.Popen(self.argv, stdout=subprocess.PIPE, text=True, start_new_session=True,
                                     preexec_fn=lambda: apply_in_child(nice, sched, True, rt))
        ready = threading.Event()
        threading.Thread(target=lambda: self.proc.stdout.readline().strip() == "ready" and ready.set(),
                         daemon=True).start()
        if not ready.wait(self.ready_timeout_s):
            self.proc.kill()
            raise RuntimeError(f"bench probe not subscribed within {self.ready_timeout_s:g} s")
        return self

    def __exit__(self, *exc) -> None:
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        if self.out_npz.is_file():
            with np.load(self.out_npz) as z:
                for name in NAMES:
                    sent = z[f"{name}_sent_ns"].tolist() if f"{name}_sent_ns" in z.files else None
                    for k, (s, t) in enumerate(zip(z[f"{name}_stamp_ns"].tolist(), z[f"{name}_arrival_ns"].tolist())):
                        self.log.add(name, s, t, NO_TIME if sent is None else sent[k])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m tools.bench_probe", description=__doc__.splitlines()[0])
    p.add_argument("--config")
    p.add_argument("--set", action="append", default=[])
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    from services.app.system_config import load_system_config
    from shared import topics
    from transport.node import Node
    from transport.pubsub import sample_sent_ns

    log, stop = ArrivalLog(), threading.Event()
    signal.signal(signal.SIGTERM, lambda *a: stop.set())
    with Node("bench", load_system_config(args.config, args.set).transport, handle_signals=False) as node:
        node.subscriber(topics.FRAME, handler=log.handler("frame", sent=sample_sent_ns))
        node.subscriber(topics.STATE, policy="all", handler=log.handler("state", sent=sample_sent_ns))
        node.subscriber(topics.FEATURES, policy="all", handler=log.handler("features", sent=sample_sent_ns))
        node.subscriber(topics.DEPTH_FUSED, handler=log.handler("depth", sent=sample_sent_ns))
        node.subscriber(topics.SUBMAP, handler=log.handler("map", sent=sample_sent_ns))
        print("ready", flush=True)
        while not stop.wait(0.5):
            pass
    arrays = {}
    for name in NAMES:
        arrays[f"{name}_stamp_ns"], arrays[f"{name}_arrival_ns"] = log.get(name)
        arrays[f"{name}_sent_ns"] = log.sent_column(name)
    np.savez(args.out, **arrays)
    return 0


if __name__ == "__main__":
    sys.exit(main())
