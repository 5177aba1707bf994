"""Transport benchmark: two real processes on one host talking through Zenoh.

The parent process runs the router and the measuring side; a child process
(``python -m tools.bench_transport --role send|pong ...``) is the other side. Peers learn about each
other from the router and then talk directly. Cases:

* round trip of 64 B raw payloads and of a typed ImuSample (ping-pong, the next ping is sent from
  the pong callback, so each sample is one full round trip through both processes);
* one-way latency and delivered rate of 786 KB frames (a 768x1024 uint8 MultiCameraFrame, the
  budget's "786 KB image") at 30 Hz, with shared memory on and off, plus a 512x384 float32
  DepthFrame (depth and sigma, 1.5 MB) with shared memory. One-way latency is the receiver's
  ``time.time_ns()`` after decoding minus the sender's ``time.time_ns()`` stamped just before
  encoding (same host clock), so it includes encode, copies and decode.

Budget (BRIEF sec. 7): 786 KB with SHM p50 <= 1 ms, p99 <= 3 ms, no drops; 64 B round trip p50 <= 0.3 ms.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import numpy as np

from shared.messages import Header, ImuSample, MultiCameraFrame, DepthFrame
from transport.config import TransportConfig
from transport.pubsub import Publisher, Subscriber
from transport.session import open_session, free_local_port

REPO = Path(__file__).resolve().parents[1]
TARGETS = {"frame_shm_p50_ms": 1.0, "frame_shm_p99_ms": 3.0, "rtt_64B_p50_ms": 0.3}
PAYLOADS = ("image", "depth")


def make_message(kind: str, stamp_ns: int, seq: int, data: dict) -> object:
    if kind == "image":
        return MultiCameraFrame(header=Header(stamp_ns=stamp_ns, seq=seq, frame_id="rig"), images=(data["image"],),
                                camera_names=("cam0",), stamps_ns=np.array([stamp_ns], np.int64))
    return DepthFrame(header=Header(stamp_ns=stamp_ns, seq=seq, frame_id="cam0"), depth=data["depth"],
                      sigma=data["sigma"], K=np.eye(3), T_WC=np.eye(4), source="bench")


def message_type(kind: str) -> type:
    return MultiCameraFrame if kind == "image" else DepthFrame


def session_cfg(connect: str, namespace: str, shm: bool) -> TransportConfig:
    return TransportConfig(namespace=namespace, connect=[connect], listen=["tcp/127.0.0.1:0"], shared_memory=shm)


def summary_ms(samples_ns: list[int] | np.ndarray) -> dict:
    a = np.asarray(samples_ns, dtype=float) / 1e6
    if a.size == 0:
        return {"n": 0, "p50_ms": None, "p90_ms": None, "p99_ms": None, "max_ms": None, "mean_ms": None}
    p50, p90, p99 = np.percentile(a, [50, 90, 99])
    return {"n": int(a.size), "p50_ms": float(p50), "p90_ms": float(p90), "p99_ms": float(p99),
            "max_ms": float(a.max()), "mean_ms": float(a.mean())}


# ----------------------------------------------------------------------------- child roles

def role_send(args: argparse.Namespace) -> int:
    """Publish frames at ``--rate`` for ``--duration`` seconds; print a JSON line with counters."""
    cfg = session_cfg(args.connect, args.namespace, bool(args.shm))
    rng = np.random.default_rng(0)
    data = {"image": rng.integers(0, 255, (768, 1024), dtype=np.uint8),
            "depth": rng.random((384, 512), dtype=np.float32), "sigma": rng.random((384, 512), dtype=np.float32)}
    with open_session(cfg) as session:
        pub = Publisher(session, f"{args.namespace}/bench/frame", message_type(args.payload), cfg, block=True)
        ok = pub.wait_for_subscribers(10.0)
        time.sleep(0.2)  # let the direct peer link settle after discovery
        period = 1.0 / args.rate
        t0 = time.perf_counter()
        n = int(round(args.duration * args.rate))
        size = 0
        for i in range(n):
            delay = t0 + i * period - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            size = pub.publish(make_message(args.payload, time.time_ns(), i, data))
        time.sleep(0.3)  # let the last frames arrive before the session closes
        print(json.dumps({"sent": pub.sent, "sent_shm": pub.sent_shm, "shm_fallbacks": pub.shm_fallbacks,
                          "payload_bytes": size, "had_subscriber": ok}), flush=True)
        pub.close()
    return 0


def role_pong(args: argparse.Namespace) -> int:
    """Echo every ping (raw or typed) on the pong key until an empty ping arrives."""
    cfg = session_cfg(args.connect, args.namespace, True)
    done = threading.Event()
    with open_session(cfg) as session:
        raw_out = session.declare_publisher(f"{args.namespace}/bench/pong", express=True)
        typed_out = Publisher(session, f"{args.namespace}/bench/pong_typed", ImuSample, cfg, express=True, prepare_shm=False)

        def on_raw(sample) -> None:
            payload = sample.payload.to_bytes()
            if not payload:
                done.set()
                return
            raw_out.put(payload)

        def on_typed(msg) -> None:
            typed_out.publish(msg)

        raw_sub = session.declare_subscriber(f"{args.namespace}/bench/ping", on_raw)
        typed_sub = Subscriber(session, f"{args.namespace}/bench/ping_typed", ImuSample, handler=on_typed)
        done.wait(120.0)  # the parent sends an empty ping when it is done
        typed_sub.close()
        raw_sub.undeclare()
        typed_out.close()
        raw_out.undeclare()
    print(json.dumps({"pong": "done"}), flush=True)
    return 0


# ----------------------------------------------------------------------------- parent side

def spawn(role: str, args: argparse.Namespace, connect: str, namespace: str, **extra: object) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "tools.bench_transport", "--role", role, "--connect", connect,
           "--namespace", namespace, "--duration", str(args.duration)]
    for k, v in extra.items():
        cmd += [f"--{k}", str(v)]
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def child_result(proc: subprocess.Popen, timeout: float) -> dict:
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        raise RuntimeError(f"benchmark child timed out; stderr:\n{err[-2000:]}")
    lines = [ln for ln in out.splitlines() if ln.startswith("{")]
    if proc.returncode != 0 or not lines:
        raise RuntimeError(f"benchmark child failed (rc {proc.returncode}); stderr:\n{err[-2000:]}")
    return json.loads(lines[-1])


def measure_rtt(args: argparse.Namespace, connect: str) -> dict:
    ns = f"sigmaslam/bench-{uuid.uuid4().hex[:8]}"
    cfg = session_cfg(connect, ns, True)
    child = spawn("pong", args, connect, ns)
    results = {}
    try:
        with open_session(cfg) as session:
            results["rtt_64B"] = _ping_raw(session, ns, args.samples)
            results["rtt_imu"] = _ping_typed(session, ns, cfg, args.samples)
            session.put(f"{ns}/bench/ping", b"")  # tells the child to stop
            child_result(child, 10.0)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    return results


def _chain(send, samples: int, warmup: int) -> tuple:
    """Ping-pong bookkeeping: on_pong records the round trip and sends the next ping."""
    rtts: list[int] = []
    done = threading.Event()
    state = {"t": 0, "k": 0}

    def on_pong(_payload) -> None:
        now = time.perf_counter_ns()
        state["k"] += 1
        if state["k"] > warmup:
            rtts.append(now - state["t"])
        if len(rtts) >= samples:
            done.set()
            return
        state["t"] = time.perf_counter_ns()
        send()

    def start() -> None:
        state["t"] = time.perf_counter_ns()
        send()

    return rtts, done, on_pong, start


def _run_chain(samples: int, started: threading.Event, start, done: threading.Event) -> None:
    # until the child answers, keep sending single pings; then the chain runs in the callbacks
    deadline = time.monotonic() + 15.0
    while not started.is_set() and time.monotonic() < deadline:
        start()
        started.wait(0.05)
    if not done.wait(max(5.0, samples * 0.01)):
        raise RuntimeError("ping-pong stalled (lost message or child gone)")


def _ping_raw(session, ns: str, samples: int) -> dict:
    payload = bytes(64)
    pub = session.declare_publisher(f"{ns}/bench/ping", express=True)
    started = threading.Event()
    rtts, done, on_pong, start = _chain(lambda: pub.put(payload), samples, warmup=100)

    def cb(sample) -> None:
        if not started.is_set():
            started.set()
        on_pong(sample.payload)

    sub = session.declare_subscriber(f"{ns}/bench/pong", cb)
    try:
        _run_chain(samples, started, start, done)
    finally:
        sub.undeclare()
        pub.undeclare()
    return dict(summary_ms(rtts), payload_bytes=len(payload))


def _ping_typed(session, ns: str, cfg: TransportConfig, samples: int) -> dict:
    pub = Publisher(session, f"{ns}/bench/ping_typed", ImuSample, cfg, express=True, prepare_shm=False)
    msg = ImuSample(header=Header(stamp_ns=0, frame_id="S"), omega_S=np.zeros(3), acc_S=np.array([0, 0, 9.81]))
    started = threading.Event()
    rtts, done, on_pong, start = _chain(lambda: pub.publish(msg), samples, warmup=100)

    def cb(m) -> None:
        if not started.is_set():
            started.set()
        on_pong(m)

    sub = Subscriber(session, f"{ns}/bench/pong_typed", ImuSample, handler=cb)
    try:
        _run_chain(samples, started, start, done)
    finally:
        sub.close()
        pub.close()
    from shared.codec import encode
    return dict(summary_ms(rtts), payload_bytes=len(encode(msg)))


def measure_frames(args: argparse.Namespace, connect: str, payload: str, shm: bool) -> dict:
    ns = f"sigmaslam/bench-{uuid.uuid4().hex[:8]}"
    cfg = session_cfg(connect, ns, shm)
    latencies: list[int] = []
    seqs: list[int] = []

    def on_frame(msg) -> None:
        latencies.append(time.time_ns() - msg.header.stamp_ns)
        seqs.append(msg.header.seq)

    with open_session(cfg) as session:
        sub = Subscriber(session, f"{ns}/bench/frame", message_type(payload), "all", 1024, handler=on_frame)
        child = spawn("send", args, connect, ns, payload=payload, shm=int(shm), rate=args.rate)
        try:
            sender = child_result(child, args.duration + 30.0)
        finally:
            if child.poll() is None:
                child.kill()
                child.wait()
        time.sleep(0.1)
        sub.close()
    delivered = len(latencies)
    lost = sender["sent"] - delivered
    return dict(summary_ms(latencies), name=f"{payload} {'shm' if shm else 'plain'}", payload=payload, shm=shm,
                payload_bytes=sender["payload_bytes"], rate_hz=args.rate, duration_s=args.duration,
                sent=sender["sent"], sent_shm=sender["sent_shm"], received_shm=sub.received_shm,
                delivered=delivered, drops=lost + sub.dropped, latencies_ms=[round(x / 1e6, 4) for x in latencies], out_of_order=int(np.sum(np.diff(seqs) <= 0)) if seqs else 0)


def benchmark(args: argparse.Namespace) -> dict:
    port = args.port or free_local_port()
    connect = f"tcp/127.0.0.1:{port}"
    router_cfg = TransportConfig(router_listen=[connect], shared_memory=True)
    result = {"host": platform.node(), "cpus": os.cpu_count(), "python": platform.python_version(),
              "started_ns": time.time_ns(), "targets": TARGETS}
    with open_session(router_cfg, role="router"):
        result.update(measure_rtt(args, connect))
        cases = [("image", True), ("image", False), ("depth", True)]
        result["frames"] = [measure_frames(args, connect, payload, shm) for payload, shm in cases]
    shm_image = result["frames"][0]
    result["pass"] = {
        "frame_shm_p50": shm_image["p50_ms"] is not None and shm_image["p50_ms"] <= TARGETS["frame_shm_p50_ms"],
        "frame_shm_p99": shm_image["p99_ms"] is not None and shm_image["p99_ms"] <= TARGETS["frame_shm_p99_ms"],
        "frame_shm_no_drops": shm_image["drops"] == 0,
        "rtt_64B_p50": result["rtt_64B"]["p50_ms"] is not None and result["rtt_64B"]["p50_ms"] <= TARGETS["rtt_64B_p50_ms"],
    }
    return result


def format_table(result: dict) -> str:
    def f(v) -> str:
        return "   -  " if v is None else f"{v:6.3f}"

    rows = [f"{'case':<22} {'bytes':>8} {'p50':>6} {'p90':>6} {'p99':>6} {'max':>6}  {'delivered/sent':>14} {'drops':>5}"]
    for key in ("rtt_64B", "rtt_imu"):
        r = result[key]
        rows.append(f"{'round trip ' + key[4:]:<22} {r['payload_bytes']:>8} {f(r['p50_ms'])} {f(r['p90_ms'])} "
                    f"{f(r['p99_ms'])} {f(r['max_ms'])}  {r['n']:>14} {'-':>5}")
    for r in result["frames"]:
        rows.append(f"{'one-way ' + r['name']:<22} {r['payload_bytes']:>8} {f(r['p50_ms'])} {f(r['p90_ms'])} "
                    f"{f(r['p99_ms'])} {f(r['max_ms'])}  {str(r['delivered']) + '/' + str(r['sent']):>14} {r['drops']:>5}")
    rows.append("latencies in ms; one-way at %g Hz for %g s; targets: %s" % (
        result["frames"][0]["rate_hz"], result["frames"][0]["duration_s"],
        ", ".join(f"{k} <= {v}" for k, v in TARGETS.items())))
    rows.append("pass: " + ", ".join(f"{k}={'yes' if v else 'NO'}" for k, v in result["pass"].items()))
    return "\n".join(rows)


# ----------------------------------------------------------------------------- CLI

def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--duration", type=float, default=10.0, help="seconds of each 30 Hz frame case [s]")
    p.add_argument("--rate", type=float, default=30.0, help="frame rate of the one-way cases [Hz]")
    p.add_argument("--samples", type=int, default=2000, help="round trips measured per ping-pong case")
    p.add_argument("--port", type=int, default=0, help="router TCP port on 127.0.0.1 (0: a free one)")
    p.add_argument("--json", metavar="PATH", help="write the full result as JSON")


def main(args: argparse.Namespace) -> int:
    if args.duration <= 0 or args.rate <= 0 or args.samples < 1:
        print("bench transport: --duration, --rate and --samples must be positive", file=sys.stderr)
        return 2
    result = benchmark(args)
    print(format_table(result))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))
        print(f"wrote {args.json}")
    return 0


def _child_main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="transport benchmark (child roles; use 'python -m tools bench transport')")
    add_arguments(p)
    p.add_argument("--role", choices=("parent", "send", "pong"), default="parent")
    p.add_argument("--connect", default="")
    p.add_argument("--namespace", default="sigmaslam/bench")
    p.add_argument("--payload", choices=PAYLOADS, default="image")
    p.add_argument("--shm", type=int, default=1)
    args = p.parse_args(argv)
    if args.role == "send":
        return role_send(args)
    if args.role == "pong":
        return role_pong(args)
    return main(args)


if __name__ == "__main__":
    sys.exit(_child_main())
