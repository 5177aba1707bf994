"""The recorder's loop (``sigmaslam record``): records every topic (or ``--key EXPR``) to MCAP; ``--recover`` repairs a
cut file (services/recorder/node.py declares its topics).

The Zenoh callback only copies the payload and the receive time into a bounded keep-all queue
(bounded in messages and bytes; beyond either bound the message is dropped and counted); the main
thread decodes, writes native and Foxglove channels, and closes a chunk at least every
``recorder.flush_period_s``. SIGTERM/SIGINT: stop subscribing, write what is queued, close the
file with summary and index. Queue counters and the write timer go out in ``stats/recorder``.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import threading
import time
from pathlib import Path

import zenoh

from services.recorder.mcap_writer import RecordingError, RecordingWriter
from services.recorder.recovery import RecoveryError, recover
from shared.config import to_yaml
from services.recorder.node import RecorderNode
from transport.node import Node
from transport.queues import BoundedQueue, Empty

log = logging.getLogger("sigmaslam.record")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--key", metavar="EXPR", help="Zenoh key expression to record (default: '<namespace>/**')")
    p.add_argument("--recover", metavar="BROKEN.mcap", help="rebuild a complete indexed file from a cut one into --out, then exit")


def fresh_path(out: Path) -> Path:
    """``out``, or ``<stem>.<n><suffix>`` for the first free n when ``out`` exists: a recorder restarted after
    a crash never overwrites the cut recording of its previous life (recover that with --recover)."""
    if not out.exists():
        return out
    n = 1
    while (alt := out.with_name(f"{out.stem}.{n}{out.suffix}")).exists():
        n += 1
    log.warning("%s exists (a previous recording, e.g. cut by a crash): recording to %s instead", out, alt)
    return alt


def default_output(output_dir: str) -> Path:
    return Path(output_dir) / f"sigmaslam-{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}-{os.getpid()}.mcap"


class _ByteBudget:
    """Bytes waiting in the queue, against a hard bound (shared by the callback and the writer)."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.used = 0
        self._lock = threading.Lock()

    def take(self, n: int) -> bool:
        with self._lock:
            if self.used + n > self.limit:
                return False
            self.used += n
            return True

    def give(self, n: int) -> None:
        with self._lock:
            self.used -= n


def record(cfg, args: argparse.Namespace) -> int:
    """Record with the system config ``cfg`` (the recorder's main), or repair a cut file (``--recover``); returns the
    exit status."""
    if args.recover:
        if not args.out:
            print("sigmaslam record --recover needs --out FIXED.mcap", file=sys.stderr)
            return 2
        try:
            report = recover(args.recover, args.out)
        except (RecoveryError, OSError) as exc:
            print(f"sigmaslam record --recover: {exc}", file=sys.stderr)
            return 1
        state = "complete input" if report.complete else f"cut at byte {report.stopped_at_byte} of {report.input_bytes} ({report.reason or 'end of file'})"
        print(f"recovered {report.messages} messages on {report.channels} channels, {report.metadata} metadata "
              f"into {args.out}: {state}", flush=True)
        return 0

    rc = cfg.recorder
    key = args.key or rc.key_expr or f"{cfg.transport.namespace.rstrip('/')}/**"
    out = fresh_path(Path(args.out) if args.out else default_output(rc.output_dir))
    # the node (and with it the SIGTERM/SIGINT handling) comes first: a stop signal that arrives once the file
    # exists must find a handler that closes it, not the default action that would leave it without a summary
    with Node("recorder", cfg.transport, declared=RecorderNode) as node:
        try:
            writer = RecordingWriter(out, chunk_size_bytes=rc.chunk_size_bytes, compression=rc.compression,
                                     foxglove_mirror=rc.foxglove, config_yaml=to_yaml(cfg))
        except RecordingError as exc:
            print(f"sigmaslam record: {exc}", file=sys.stderr)
            return 1
        try:
            _record(node, key, writer, rc.queue_depth, rc.queue_max_bytes, rc.flush_period_s)
        finally:
            # closed before the session: closing a session can take seconds (peers leaving), and a supervisor's
            # SIGKILL after its shutdown timeout must not find the summary unwritten
            writer.close()
    log.info("closed %s: %d messages, %d Foxglove mirror messages, %d undecodable dropped", out, writer.messages,
             writer.mirror_messages, writer.dropped_undecodable)
    print(f"recorded {writer.messages} messages to {out}", flush=True)
    return 0


def _record(node: Node, key: str, writer: RecordingWriter, depth: int, max_bytes: int, flush_period_s: float) -> None:
    queue: BoundedQueue[tuple[str, bytes, int]] = BoundedQueue("all", depth, "record")
    budget = _ByteBudget(max_bytes)
    node.stats.add_queue("record", queue.counters)
    write_timer = node.timer("write")

    def on_sample(sample: zenoh.Sample) -> None:
        t_ns = time.time_ns()
        shm = sample.payload.as_shm()
        data = bytes(shm) if shm is not None else sample.payload.to_bytes()
        if not budget.take(len(data)):
            queue.count_received()
            queue.count_drop()
            return
        if not queue.put((str(sample.key_expr), data, t_ns)):
            budget.give(len(data))

    sub = node.session.declare_subscriber(key, on_sample)
    print(f"recording {key} to {writer.path}", flush=True)
    last_flush = time.monotonic()
    pending = 0

    def write_one(item: tuple[str, bytes, int]) -> None:
        k, data, t_ns = item
        budget.give(len(data))
        with write_timer:
            writer.write(k, data, t_ns)

    try:
        while not node.stopped:
            try:
                item = queue.get(timeout=0.1)
            except Empty:
                item = None
            if item is not None:
                write_one(item)
                pending += 1
            if pending and time.monotonic() - last_flush >= flush_period_s:
                writer.flush()
                pending, last_flush = 0, time.monotonic()
    finally:
        sub.undeclare()
        for item in queue.drain():
            write_one(item)
        dropped = queue.dropped
        if dropped:
            log.warning("%d messages dropped because the writer fell behind (queue bound)", dropped)
