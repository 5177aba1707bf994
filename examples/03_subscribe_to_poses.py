"""03: subscribe to the poses of a running sigmaslam.

The back end publishes one ``EstimatorState`` per camera frame on ``<namespace>/estimator/state``: the causal body
pose ``T_WS`` (4x4, maps body points into the world W), velocity, IMU biases, a 15x15 covariance and a status
('initialising', 'tracking', 'imu_only', 'lost' or 'reset'). This script joins the same Zenoh network as a
*client* of its router and prints them, using sigmaslam's own transport pieces: the transport config of the run,
``transport.session.open_session`` and the typed ``transport.pubsub.Subscriber`` (decoding, a bounded queue,
drop counters). It publishes nothing, not even a heartbeat.

Start something that publishes poses, then this script. ``sigmaslam run`` uses a private router port and
namespace, which it writes into ``DIR/config.yaml`` at start; ``sigmaslam up`` writes its config into
``runs/<time>-<pid>/config.yaml``::

    sigmaslam run data/replicas/V1_02-vicon-a-real-s0-d25-seed0 --out out/run --realtime &
    python -m examples.03_subscribe_to_poses --config out/run/config.yaml --count 50

    sigmaslam up configs/default.yaml &          # router on tcp/127.0.0.1:7447, namespace sigmaslam/robot0
    python -m examples.03_subscribe_to_poses     # the built-in defaults match it

A program that does not want sigmaslam's ``transport`` package needs only zenoh-python and
``shared.codec.decode``: tools/zenoh_client_example.py and docs/zenoh_client.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np
import zenoh

from services.app.system_config import load_system_config
from shared import topics
from shared.geometry import R_to_quat_wxyz
from transport.pubsub import Subscriber
from transport.queues import Empty
from transport.session import open_session


def connect(tcfg, deadline: float):
    """A session with the router; a client cannot open one before the router listens (a run that was just
    started may still be starting it), so try again until ``deadline`` (time.monotonic())."""
    while True:
        try:
            return open_session(tcfg)
        except zenoh.ZError:
            if time.monotonic() >= deadline:
                raise
            time.sleep(0.5)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", help="the run's resolved config (DIR/config.yaml); default: the built-in defaults")
    ap.add_argument("--connect", help="router endpoint, e.g. tcp/127.0.0.1:7447 (default: transport.connect)")
    ap.add_argument("--namespace", help="topic prefix, e.g. sigmaslam/robot0 (default: transport.namespace)")
    ap.add_argument("--count", type=int, default=20, help="stop after this many poses (0: until --timeout)")
    ap.add_argument("--timeout", type=float, default=60.0, help="stop after this many seconds [s]")
    ap.add_argument("--print-every", type=int, default=1, help="print every n-th pose")
    args = ap.parse_args(argv)

    # 1. Where to connect: the transport section of the run's config (router endpoint, namespace). As a Zenoh
    #    client this process talks to the router only and opens no listening port of its own.
    tcfg = load_system_config(args.config, []).transport
    tcfg = dataclasses.replace(tcfg, mode="client", connect=[args.connect] if args.connect else tcfg.connect,
                               namespace=args.namespace or tcfg.namespace)
    key = topics.STATE.key_expr(tcfg.namespace)  # '<namespace>/estimator/state', from the one list of topics
    print(f"subscribing to {key} via {tcfg.connect[0]}", flush=True)

    poses: list[tuple[int, np.ndarray, str]] = []
    statuses: dict[str, int] = {}
    t_end = time.monotonic() + args.timeout
    with connect(tcfg, t_end) as session:
        # 2. A typed subscriber: each sample is decoded into a frozen EstimatorState (a payload that is not one is
        #    counted as a drop, never raised), and kept in a queue that never drops a pose ('all', 1000 deep).
        sub = Subscriber(session, key, topics.STATE.msg_type, policy="all", depth=1000, name="example03")
        try:
            while time.monotonic() < t_end and not (args.count and len(poses) >= args.count):
                try:
                    st = sub.get(timeout=0.2)
                except Empty:
                    continue
                # 3. Read the state. Stamps are int64 ns of the camera frame; 'initialising' and 'reset' states
                #    carry no usable pose (identity), so skip them as the mapping and depth services do.
                statuses[st.status] = statuses.get(st.status, 0) + 1
                if st.status in ("initialising", "reset"):
                    continue
                p_W = np.array(st.T_WS[:3, 3])  # arrays of a decoded message are read-only views: copy to keep
                q = R_to_quat_wxyz(st.T_WS[:3, :3])
                # covariance order [rot_S, p_W, v_W, gyro_bias, acc_bias]; NaN between keyframes
                sigma_p = np.sqrt(np.diag(st.covariance)[3:6])
                poses.append((int(st.header.stamp_ns), p_W, st.status))
                if (len(poses) - 1) % max(args.print_every, 1) == 0:
                    sig = f"{1e3 * sigma_p.max():.1f} mm" if np.isfinite(sigma_p).all() else "n/a"
                    print(f"t={st.header.stamp_ns} p_W=[{p_W[0]:.3f} {p_W[1]:.3f} {p_W[2]:.3f}] "
                          f"q_WS_wxyz=[{q[0]:.3f} {q[1]:.3f} {q[2]:.3f} {q[3]:.3f}] sigma_p={sig} {st.status}",
                          flush=True)
            received, dropped, _ = sub.counters()
        finally:
            sub.close()

    # 4. A summary: how many, how often (in data time), how far.
    rate = path = 0.0
    if len(poses) >= 2:
        t = np.array([p[0] for p in poses])
        rate = (len(t) - 1) / ((t[-1] - t[0]) * 1e-9) if t[-1] > t[0] else 0.0
        path = float(np.linalg.norm(np.diff([p[1] for p in poses], axis=0), axis=1).sum())
    print(f"{len(poses)} poses ({statuses}), {rate:.1f} Hz in data time, {path:.2f} m; "
          f"subscriber received {received}, dropped {dropped}", flush=True)
    return {"poses": len(poses), "statuses": statuses, "rate_hz": rate, "path_m": path,
            "positions": [p[1].tolist() for p in poses], "dropped": dropped}


if __name__ == "__main__":
    main()
