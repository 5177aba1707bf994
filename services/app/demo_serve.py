"""Show a finished run folder in the web viewer: a private router, the viewer process, and the run's results
(submap meshes with their poses, the causal and final trajectories) published to it once, then re-published
every few seconds so that a page opened later also gets them.

Reads what ``sigmaslam run`` wrote: ``config.yaml``, ``mapping.json`` + ``submaps/submap_NNN.ply`` (each in
its submap frame M), ``trajectory_causal.txt`` and, if present, ``trajectory_final.txt`` (TUM).
"""
from __future__ import annotations

import json
import logging
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from services.app.system_config import load_system_config
from shared import topics
from shared.codec import Header
from shared.euroc import read_tum
from shared.geometry import pose_from_pq
from shared.messages import EstimatorState, Keyframes, SubmapMesh
from transport.node import Node
from transport.session import open_session, free_local_port

log = logging.getLogger("sigmaslam.demo")


def load_submaps(out: Path) -> list[SubmapMesh]:
    """The run's submap meshes as SubmapMesh messages (empty list if the run wrote no map)."""
    import open3d as o3d

    meta_path = out / "mapping.json"
    if not meta_path.is_file():
        return []
    msgs = []
    for sm in json.loads(meta_path.read_text()).get("submaps", []):
        ply = out / "submaps" / f"submap_{int(sm['id']):03d}.ply"
        if not ply.is_file():
            continue
        mesh = o3d.io.read_triangle_mesh(str(ply))
        v = np.asarray(mesh.vertices, np.float32)
        f = np.asarray(mesh.triangles, np.int32)
        if len(v) == 0 or len(f) == 0:
            continue
        msgs.append(SubmapMesh(header=Header(stamp_ns=0, seq=len(msgs), frame_id="W"), submap_id=int(sm["id"]),
                               T_WM=np.asarray(sm["T_WM"], np.float64), vertices_M=v, faces=f,
                               vertex_colors=np.zeros((0, 3), np.uint8)))
    return msgs


def load_states(path: Path) -> list[EstimatorState]:
    """A TUM trajectory as EstimatorState messages (velocity, biases and covariance unknown: zeros)."""
    if not path.is_file():
        return []
    traj = read_tum(path)
    T = pose_from_pq(traj.p_WS, traj.q_WS_wxyz)
    z3, z15 = np.zeros(3), np.zeros((15, 15))
    return [EstimatorState(header=Header(stamp_ns=int(t), seq=i, frame_id="W"), T_WS=T[i], v_W=z3, gyro_bias=z3,
                           acc_bias=z3, covariance=z15, status="tracking")
            for i, t in enumerate(traj.stamps_ns)]


def serve_run(out: Path, config: str | None, overrides: list[str], seconds: float) -> None:
    port = free_local_port()
    cfg = load_system_config(config, [*overrides, f"transport.connect=[tcp/127.0.0.1:{port}]",
                                      f"transport.router_listen=[tcp/127.0.0.1:{port}]",
                                      "transport.namespace=sigmaslam/demo-serve"])
    serve_cfg = out / "serve_config.yaml"
    from shared.config import to_yaml

    serve_cfg.write_text(to_yaml(cfg))
    submaps = load_submaps(out)
    states = load_states(out / "trajectory_causal.txt")
    final = load_states(out / "trajectory_final.txt")
    router = open_session(cfg.transport, role="router")
    viewer = subprocess.Popen([sys.executable, "-m", "services.app.cli", "viewer", str(serve_cfg)])
    try:
        with Node("demo-serve", cfg.transport) as node:
            pub_mesh = node.publisher(topics.SUBMAP)
            pub_state = node.publisher(topics.STATE)
            pub_kf = node.publisher(topics.KEYFRAMES)
            pub_mesh.wait_for_subscribers(30.0)
            deadline = time.monotonic() + seconds
            while time.monotonic() < deadline and viewer.poll() is None and not node.stopped:
                for s in states:
                    pub_state.publish(s)
                if final:
                    T = np.stack([s.T_WS for s in final])
                    pub_kf.publish(Keyframes(header=Header(stamp_ns=final[-1].header.stamp_ns, seq=pub_kf.next_seq,
                                                           frame_id="W"),
                                             ids=np.arange(len(final), dtype=np.int64),
                                             stamps_ns=np.array([s.header.stamp_ns for s in final], np.int64),
                                             T_WS=T))
                for m in submaps:
                    pub_mesh.publish(m)
                node.wait(min(10.0, max(0.0, deadline - time.monotonic())))
    finally:
        viewer.terminate()
        try:
            viewer.wait(10)
        except subprocess.TimeoutExpired:
            viewer.kill()
        router.close()
