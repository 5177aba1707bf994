"""A third-party Zenoh client of sigmaslam: poses and submap meshes with plain zenoh-python.

Only two things come from sigmaslam: :func:`shared.codec.decode` (bytes -> message dataclass) and the
message classes it returns (importing :mod:`shared.messages` registers them). No transport/ code::

    python -m tools.zenoh_client_example --connect tcp/127.0.0.1:7447 --namespace sigmaslam/robot0

prints one line per causal pose (at most ``--pose-every``-th) and one per submap mesh; ``--count N``
exits after N printed lines. See docs/zenoh_client.md.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading

import numpy as np
import zenoh

from shared import messages  # noqa: F401  (registers the message types with the codec)
from shared.codec import DecodeError, decode
from shared.geometry import R_to_quat_wxyz


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="print sigmaslam poses and submap meshes")
    ap.add_argument("--connect", default="tcp/127.0.0.1:7447", help="Zenoh router endpoint")
    ap.add_argument("--namespace", default="sigmaslam/robot0", help="sigmaslam namespace (transport.namespace)")
    ap.add_argument("--pose-every", type=int, default=10, help="print every n-th pose")
    ap.add_argument("--count", type=int, default=0, help="exit after this many printed lines (0: run until Ctrl-C)")
    args = ap.parse_args(argv)

    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("client"))  # a client talks to the router only
    conf.insert_json5("connect/endpoints", json.dumps([args.connect]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    printed, done = [0], threading.Event()
    lock = threading.Lock()

    def emit(line: str) -> None:
        with lock:
            if done.is_set():  # callbacks still running after --count was reached
                return
            print(line, flush=True)
            printed[0] += 1
            if args.count and printed[0] >= args.count:
                done.set()

    def on_state(sample: zenoh.Sample) -> None:
        try:
            msg = decode(sample.payload.to_bytes(), messages.EstimatorState)
        except DecodeError as exc:  # not a sigmaslam message of this type: skip it
            print(f"skipped a bad pose payload: {exc}", file=sys.stderr)
            return
        if msg.header.seq % max(args.pose_every, 1) == 0:
            p = msg.T_WS[:3, 3]
            q = R_to_quat_wxyz(msg.T_WS[:3, :3])
            emit(f"pose t={msg.header.stamp_ns} p_W=[{p[0]:.3f} {p[1]:.3f} {p[2]:.3f}] "
                 f"q_WS_wxyz=[{q[0]:.3f} {q[1]:.3f} {q[2]:.3f} {q[3]:.3f}] status={msg.status}")

    def on_submap(sample: zenoh.Sample) -> None:
        try:
            msg = decode(sample.payload.to_bytes(), messages.SubmapMesh)
        except DecodeError as exc:
            print(f"skipped a bad mesh payload: {exc}", file=sys.stderr)
            return
        centre_W = msg.T_WM[:3, :3] @ np.mean(msg.vertices_M, axis=0) + msg.T_WM[:3, 3] if len(msg.vertices_M) else msg.T_WM[:3, 3]
        emit(f"submap {msg.submap_id}: {len(msg.vertices_M)} vertices, {len(msg.faces)} faces, "
             f"centre_W=[{centre_W[0]:.2f} {centre_W[1]:.2f} {centre_W[2]:.2f}]")

    ns = args.namespace.rstrip("/")
    with zenoh.open(conf) as session:
        subs = [session.declare_subscriber(f"{ns}/estimator/state", on_state),
                session.declare_subscriber(f"{ns}/map/submap", on_submap)]
        try:
            while not done.wait(0.2):
                pass
        except KeyboardInterrupt:
            pass
        for s in subs:
            s.undeclare()
    return 0


if __name__ == "__main__":
    sys.exit(main())
