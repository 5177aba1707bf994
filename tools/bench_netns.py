"""``python -m tools bench netns``: latency of pipeline messages across a host boundary vs on one host.

Three real processes per case: a ``sigmaslam router``, a sender and a receiver (``python -m
tools.bench_netns --role send|recv``). Cases:

* ``host client``: all three in this network namespace on loopback, sender and receiver as Zenoh
  clients, so every message takes the router hop, as in a multi-host deployment;
* ``netns client``: the router in its own network namespace, sender and receiver each in another
  one, linked to the router's by veth pairs (:mod:`tools.netns_lab`; needs root) -- the multi-host
  layout of configs/multihost, with the kernel's veth in place of a wire;
* ``netns 3 routers``: the configs/multihost layout: a router per host, linked to the hub router,
  sender and receiver clients of their own host's router (three router hops);
* ``host peer+shm``: the default single-host deployment (peers talking directly, shared memory), for reference.

Payloads: ``estimator/state`` (an EstimatorState, ~2.3 KB, at 30 Hz) and ``depth/fused`` (a
512x384 float32 depth + sigma DepthFrame, 1.5 MB, at 10 Hz). One-way latency is the receiver's
``time.time_ns()`` after decoding minus the sender's stamp taken just before encoding (all namespaces
share one kernel clock), so it includes encoding, the router hop and decoding.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import numpy as np

from shared import topics
from shared.messages import DepthFrame, EstimatorState, Header
from tools.bench_transport import summary_ms
from tools.netns_lab import NetnsLab, unavailable_reason
from transport.config import TransportConfig
from transport.pubsub import Publisher, Subscriber
from transport.session import open_session

REPO = Path(__file__).resolve().parents[1]
PAYLOADS = {"state": (topics.STATE, 30.0), "depth": (topics.DEPTH_FUSED, 10.0)}


def make_message(payload: str, seq: int, data: dict) -> object:
    header = Header(stamp_ns=time.time_ns(), seq=seq, frame_id="W" if payload == "state" else "cam0")
    if payload == "state":
        return EstimatorState(header=header, T_WS=np.eye(4), v_W=np.zeros(3), gyro_bias=np.zeros(3),
                              acc_bias=np.zeros(3), covariance=data["cov"])
    return DepthFrame(header=header, depth=data["depth"], sigma=data["sigma"], K=np.eye(3), T_WC=np.eye(4),
                      source="fused")


def child_cfg(args: argparse.Namespace) -> TransportConfig:
    return TransportConfig(namespace=args.namespace, mode=args.mode, connect=[args.connect],
                           listen=["tcp/127.0.0.1:0"], shared_memory=bool(args.shm))


# ----------------------------------------------------------------------------- child roles

def role_send(args: argparse.Namespace) -> int:
    topic, _ = PAYLOADS[args.payload]
    cfg = child_cfg(args)
    rng = np.random.default_rng(0)
    data = {"cov": np.eye(15) * 1e-3, "depth": rng.random((384, 512), dtype=np.float32) * 5,
            "sigma": rng.random((384, 512), dtype=np.float32)}
    with open_session(cfg) as session:
        pub = Publisher(session, topic.key_expr(args.namespace), topic.msg_type, cfg, block=True,
                        prepare_shm=args.payload == "depth" and cfg.shared_memory)
        ok = pub.wait_for_subscribers(15.0)
        time.sleep(0.3)  # let routes settle after discovery
        n = int(round(args.duration * args.rate))
        t0 = time.perf_counter()
        size = 0
        for i in range(n):
            delay = t0 + i / args.rate - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            size = pub.publish(make_message(args.payload, i, data))
        time.sleep(0.5)
        session.put(f"{args.namespace}/bench/end", b"end")
        time.sleep(0.2)
        print(json.dumps({"sent": pub.sent, "payload_bytes": size, "had_subscriber": ok}), flush=True)
        pub.close()
    return 0


def role_recv(args: argparse.Namespace) -> int:
    topic, _ = PAYLOADS[args.payload]
    cfg = child_cfg(args)
    lat: list[int] = []
    end = threading.Event()

    def on_msg(msg) -> None:
        lat.append(time.time_ns() - msg.header.stamp_ns)

    with open_session(cfg) as session:
        sub = Subscriber(session, topic.key_expr(args.namespace), topic.msg_type, "all", 4096, handler=on_msg)
        marker = session.declare_subscriber(f"{args.namespace}/bench/end", lambda _s: end.set())
        print(json.dumps({"ready": True}), flush=True)
        end.wait(args.duration + 60.0)
        marker.undeclare()
        sub.close()
    print(json.dumps({"latencies_ns": lat, "dropped": sub.dropped}), flush=True)
    return 0


# ----------------------------------------------------------------------------- parent side

def _python(role: str, args: argparse.Namespace, **kw: object) -> list[str]:
    cmd = [sys.executable, "-m", "tools.bench_netns", "--role", role, "--duration", str(args.duration)]
    for k, v in kw.items():
        cmd += [f"--{k}", str(v)]
    return cmd


def _env() -> dict:
    return dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))


def _last_json(proc: subprocess.Popen, timeout: float) -> dict:
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        raise RuntimeError(f"bench child timed out; stderr:\n{err[-1500:]}")
    lines = [ln for ln in out.splitlines() if ln.startswith("{")]
    if proc.returncode != 0 or not lines:
        raise RuntimeError(f"bench child failed (rc {proc.returncode}); stderr:\n{err[-1500:]}")
    return json.loads(lines[-1])


def _wait_line(proc: subprocess.Popen, needle: str, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if needle in line:
            return
        if not line and proc.poll() is not None:
            break
    raise RuntimeError(f"child did not print {needle!r} (rc {proc.poll()}): {proc.stderr.read()[-1500:] if proc.poll() is not None else ''}")


def _router_argv(listen: str, connect: str = "") -> list[str]:
    argv = [sys.executable, "-m", "services.app.cli", "router", "--listen", listen]
    return argv + (["--set", f"transport.router_connect=[{connect}]"] if connect else [])


def run_case(args: argparse.Namespace, name: str, start, routers: list[tuple[object, list[str]]], send_connect: str,
             recv_connect: str, send_where, recv_where, mode: str, shm: bool) -> list[dict]:
    """The routers, then for each payload a receiver and a sender; ``start(where, argv, popen_kw)`` starts a process."""
    pipe = dict(stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO, env=_env())
    started = []
    rows = []
    try:
        for where, argv in routers:
            started.append(start(where, argv, pipe))
            _wait_line(started[-1], "listening")
        for payload, (_topic, rate) in PAYLOADS.items():
            ns = f"sigmaslam/bench-{uuid.uuid4().hex[:8]}"
            common = dict(payload=payload, namespace=ns, mode=mode, shm=int(shm), rate=rate)
            recv = start(recv_where, _python("recv", args, connect=recv_connect, **common), pipe)
            _wait_line(recv, "ready")
            send = start(send_where, _python("send", args, connect=send_connect, **common), pipe)
            sent = _last_json(send, args.duration + 60.0)
            got = _last_json(recv, 30.0)
            lat = got["latencies_ns"]
            rows.append(dict(summary_ms(lat), case=name, payload=payload, rate_hz=rate,
                             payload_bytes=sent["payload_bytes"], sent=sent["sent"], delivered=len(lat),
                             drops=sent["sent"] - len(lat)))
    finally:
        for router in started:
            router.terminate()
            try:
                router.wait(5.0)
            except subprocess.TimeoutExpired:
                router.kill()
    return rows


def benchmark(args: argparse.Namespace) -> dict:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    local = f"tcp/127.0.0.1:{port}"

    def start_local(_where, argv, kw):
        return subprocess.Popen(argv, **kw)

    result = {"duration_s": args.duration, "rows": []}
    result["rows"] += run_case(args, "host client", start_local, [(None, _router_argv(local))], local, local,
                               None, None, "client", False)
    reason = unavailable_reason()
    if reason is None:
        with NetnsLab(("sender", "receiver")) as lab:
            def start_ns(where, argv, kw):
                return lab.popen(lab.router_ns if where is None else lab.ns[where], argv, **kw)

            hub = [(None, _router_argv("tcp/0.0.0.0:7447"))]
            result["rows"] += run_case(args, "netns client", start_ns, hub, lab.endpoint("sender"),
                                       lab.endpoint("receiver"), "sender", "receiver", "client", False)
            # configs/multihost: a router per host linked to the hub; services are clients of their own router
            per_host = hub + [(h, _router_argv("tcp/127.0.0.1:7447", lab.endpoint(h))) for h in ("sender", "receiver")]
            loop = "tcp/127.0.0.1:7447"
            result["rows"] += run_case(args, "netns 3 routers", start_ns, per_host, loop, loop, "sender", "receiver",
                                       "client", False)
    else:
        result["netns_skipped"] = reason
    if not args.skip_peer:
        result["rows"] += run_case(args, "host peer+shm", start_local, [(None, _router_argv(local))], local, local,
                                   None, None, "peer", True)
    return result


def format_table(result: dict) -> str:
    def f(v) -> str:
        return "    -  " if v is None else f"{v:7.3f}"

    lines = [f"{'case':<16} {'topic':<16} {'bytes':>8} {'rate':>5} {'p50 ms':>7} {'p90 ms':>7} {'p99 ms':>7} "
             f"{'max ms':>7} {'delivered':>10}"]
    for r in result["rows"]:
        topic = PAYLOADS[r["payload"]][0].key
        lines.append(f"{r['case']:<16} {topic:<16} {r['payload_bytes']:>8} {r['rate_hz']:>5g} {f(r['p50_ms'])} "
                     f"{f(r['p90_ms'])} {f(r['p99_ms'])} {f(r['max_ms'])} {str(r['delivered']) + '/' + str(r['sent']):>10}")
    if "netns_skipped" in result:
        lines.append(f"netns case skipped: {result['netns_skipped']}")
    lines.append(f"one-way latency over {result['duration_s']:g} s per case and topic; 'client' and 'routers' cases route "
                 "every message through the router(s), no shared memory")
    return "\n".join(lines)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--duration", type=float, default=10.0, help="seconds of each case and payload [s]")
    p.add_argument("--skip-peer", action="store_true", help="leave out the single-host peer+shm reference case")
    p.add_argument("--json", metavar="PATH", help="write the full result as JSON")


def main(args: argparse.Namespace) -> int:
    if not args.duration > 0:
        print("bench netns: --duration must be positive", file=sys.stderr)
        return 2
    result = benchmark(args)
    print(format_table(result))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))
        print(f"wrote {args.json}")
    return 0


def _child_main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="netns benchmark child roles (use 'python -m tools bench netns')")
    add_arguments(p)
    p.add_argument("--role", choices=("parent", "send", "recv"), default="parent")
    p.add_argument("--connect", default="")
    p.add_argument("--namespace", default="sigmaslam/bench")
    p.add_argument("--payload", choices=tuple(PAYLOADS), default="state")
    p.add_argument("--mode", choices=("peer", "client"), default="client")
    p.add_argument("--shm", type=int, default=0)
    p.add_argument("--rate", type=float, default=30.0)
    args = p.parse_args(argv)
    if args.role == "send":
        return role_send(args)
    if args.role == "recv":
        return role_recv(args)
    return main(args)


if __name__ == "__main__":
    sys.exit(_child_main())
