"""Publish a small synthetic scene for the web viewer: coloured submap meshes, a circular causal
trajectory, keyframes, live images, depth+sigma, landmarks and stats, on the configured namespace.

Lets one try (and test) ``sigmaslam viewer`` without the pipeline::

    sigmaslam viewer configs/default.yaml &
    python -m tools.viewer_demo_publisher configs/default.yaml --duration 30

Every ``--reloc-period`` seconds the submap poses shift a little (as after a loop closure) with the
same meshes, so the viewer only moves them. Control messages received on ``control`` are printed
(``control: pause -> player``) so that a caller can check the viewer's buttons.
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np
import trimesh

from services.app.system_config import load_system_config
from services.viewer.colors import height_colors
from shared import messages as m
from shared import topics
from shared.geometry import make_T, so3_exp
from transport.node import Node

RADIUS_M = 3.0  # the body circles the submaps at this radius
SUBMAP_CENTRES = [(RADIUS_M * math.cos(a), RADIUS_M * math.sin(a), 0.6) for a in np.linspace(0, 2 * math.pi, 4, endpoint=False)]


def submap_messages(stamp_ns: int, shift_m: float = 0.0) -> list[m.SubmapMesh]:
    """One mesh per submap (spheres and boxes, ~1 m), in its own frame M; vertex colours encode a fake uncertainty."""
    out = []
    for sid, c in enumerate(SUBMAP_CENTRES):
        tm = trimesh.creation.icosphere(subdivisions=3, radius=0.8) if sid % 2 == 0 else trimesh.creation.box(extents=(1.4, 1.4, 1.4))
        v = np.asarray(tm.vertices, np.float32)
        T_WM = make_T(so3_exp(np.array([0.0, 0.0, 0.3 * sid])), np.asarray(c) + [shift_m, 0.0, 0.0])
        out.append(m.SubmapMesh(header=m.Header(stamp_ns=stamp_ns, seq=sid, frame_id="W"), submap_id=sid, T_WM=T_WM,
                                vertices_M=v, faces=np.asarray(tm.faces, np.int32),
                                vertex_colors=height_colors(v[:, 0].astype(float), (-0.8, 0.8))))
    return out


def body_pose(t_s: float) -> np.ndarray:
    a = 0.4 * t_s
    p = np.array([1.5 * math.cos(a), 1.5 * math.sin(a), 1.0])
    return make_T(so3_exp(np.array([0.0, 0.0, a + math.pi / 2])) @ so3_exp(np.array([-math.pi / 2, 0.0, 0.0])), p)


def demo_image(i: int, h: int = 480, w: int = 752) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w]
    return (((x + 4 * i) // 40 + y // 40) % 2 * 160 + 40).astype(np.uint8)


def depth_frame(stamp_ns: int, seq: int, T_WS: np.ndarray) -> m.DepthFrame:
    h, w = 96, 128
    y, x = np.mgrid[0:h, 0:w]
    depth = (1.0 + 3.0 * y / h).astype(np.float32)
    depth[:8] = np.nan
    K = np.array([[100.0, 0, w / 2], [0, 100.0, h / 2], [0, 0, 1]])
    T_SC = np.eye(4)
    return m.DepthFrame(header=m.Header(stamp_ns=stamp_ns, seq=seq, frame_id="cam0"), depth=depth,
                        sigma=(0.02 * depth ** 2).astype(np.float32), K=K, T_WC=T_WS @ T_SC, T_SC=T_SC, source="fused")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config", nargs="?", help="YAML system config (namespace and router)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--duration", type=float, default=30.0, help="seconds to publish [s]")
    ap.add_argument("--rate", type=float, default=20.0, help="state/frame rate [Hz]")
    ap.add_argument("--reloc-period", type=float, default=3.0, help="submap poses shift this often [s]")
    args = ap.parse_args(argv)
    cfg = load_system_config(args.config, args.set)
    with Node("demo", cfg.transport) as node:
        pubs = {t.key: node.publisher(t) for t in (topics.STATE, topics.KEYFRAMES, topics.SUBMAP, topics.FRAME,
                                                   topics.DEPTH_FUSED, topics.LANDMARKS)}
        node.subscriber(topics.CONTROL, handler=lambda c: print(f"control: {c.command} -> {c.target}", flush=True))
        pubs[topics.SUBMAP.key].wait_for_subscribers(5.0)
        pub_timer = node.timer("publish", budget_ms=10.0)
        t0 = time.monotonic()
        kf_T: list[np.ndarray] = []
        rng = np.random.default_rng(0)
        landmarks = np.concatenate([np.asarray(c) + rng.normal(scale=0.5, size=(60, 3)) for c in SUBMAP_CENTRES])
        i, last_reloc = 0, -1
        print("demo: publishing", flush=True)
        while not node.stopped and (t := time.monotonic() - t0) < args.duration:
            stamp = time.time_ns()
            with pub_timer:
                reloc = int(t // args.reloc_period)
                if reloc != last_reloc:  # all submaps: new on the first pass, then pose-only shifts
                    for msg in submap_messages(stamp, 0.05 * reloc):
                        pubs[topics.SUBMAP.key].publish(msg)
                    last_reloc = reloc
                T_WS = body_pose(t)
                hdr = m.Header(stamp_ns=stamp, seq=i, frame_id="W")
                pubs[topics.STATE.key].publish(m.EstimatorState(header=hdr, T_WS=T_WS, v_W=np.zeros(3), gyro_bias=np.zeros(3),
                                                                acc_bias=np.zeros(3), covariance=np.eye(15) * 1e-4))
                if i % 10 == 0:
                    kf_T.append(T_WS)
                    pubs[topics.KEYFRAMES.key].publish(m.Keyframes(header=hdr, ids=np.arange(len(kf_T), dtype=np.int64),
                                                                   stamps_ns=np.full(len(kf_T), stamp, np.int64) - np.arange(len(kf_T))[::-1],
                                                                   T_WS=np.stack(kf_T)))
                img = demo_image(i)
                pubs[topics.FRAME.key].publish(m.MultiCameraFrame(header=m.Header(stamp_ns=stamp, seq=i), images=(img, img),
                                                                  camera_names=("cam0", "cam1"), stamps_ns=np.array([stamp, stamp])))
                if i % 2 == 0:
                    pubs[topics.DEPTH_FUSED.key].publish(depth_frame(stamp, i // 2, T_WS))
                if i % 10 == 0:
                    sel = np.sort(rng.choice(len(landmarks), 30, replace=False))
                    pubs[topics.LANDMARKS.key].publish(m.Landmarks(
                        header=hdr, ids=sel.astype(np.int64), p_W=landmarks[sel], num_observations=np.full(30, 2, np.int32),
                        last_seen_ns=np.full(30, stamp, np.int64)))
            i += 1
            node.wait(max(0.0, t0 + i / args.rate - time.monotonic()))
        print(f"demo: published {i} frames", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
