"""``python -m tools bench mapping``: occupancy integration time per 512x384 depth frame at 2.5 cm, memory,
and (on a replica) mesh accuracy/completeness against the scene mesh.

Sources: ``--replica DIR`` (a ``sigmaslam synth`` folder: ground-truth depth of cam0 undistorted to a
512x384 pinhole, ground-truth poses) or, by default, a ray-cast synthetic room flown through on a
circle. Sigma is the heuristic ``--sigma-k * depth^2`` (ground-truth depth has no learned sigma).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from services.mapping.config import SensorModelConfig, SubmapConfig
from services.mapping.io import write_ply
from services.mapping.submaps import SubmapMapper


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--replica", metavar="DIR", help="replica folder (default: a ray-cast synthetic room)")
    p.add_argument("--frames", type=int, default=60, help="depth frames to integrate (0 = all of the replica)")
    p.add_argument("--stride", type=int, default=2, help="use every n-th depth frame of the replica (20 Hz -> 10 Hz)")
    p.add_argument("--voxel", type=float, default=0.025, help="voxel size [m]")
    p.add_argument("--sigma-k", type=float, default=0.005, help="heuristic sigma = k * depth^2 [1/m]")
    p.add_argument("--out", metavar="DIR", help="write mesh.ply, bench_mapping.json (and the mesh evaluation) here")
    p.add_argument("--eval", action="store_true", help="evaluate the mesh against the replica's scene mesh")


def room_frames(n: int, width: int = 512, height: int = 384):
    """(stamp_ns, depth, K, T_WC) of a camera circling inside the synthetic room."""
    from tests.raycast_depth import DepthRenderer, intrinsics, look_at, room_scene

    mesh = room_scene()
    renderer, K = DepthRenderer(mesh), intrinsics(width, height)
    for i in range(n):
        a = 2 * np.pi * i / max(n, 1)
        eye = np.array([3.0 + 1.2 * np.cos(a), 2.5 + 1.0 * np.sin(a), 1.4 + 0.2 * np.sin(3 * a)])
        T = look_at(eye, eye + np.array([np.cos(a + 0.8), np.sin(a + 0.8), -0.25]))
        yield i * 100_000_000, renderer.render(K, width, height, T), K, T


def replica_frames(folder: Path, n: int, stride: int, width: int = 512, height: int = 384):
    """(stamp_ns, depth, K, T_WC) from a replica: cam0 ground-truth depth undistorted to a pinhole of
    ``width x height`` (nearest neighbour: no mixing of depths across edges) at the ground-truth pose."""
    import cv2

    from services.mapping.poses import PoseBuffer
    from shared.camera import load_rig
    from services.app.synth.depth_io import DepthFolder
    from shared.euroc import read_trajectory
    from shared.geometry import pose_from_pq

    mav = folder / "mav0"
    depth = DepthFolder(mav / "depth0")
    cam = {c.name: c for c in load_rig(mav)}[depth.camera]
    gt = read_trajectory(mav / "state_groundtruth_estimate0" / "data.csv")
    poses = PoseBuffer(len(gt) + 1)
    for t, T in zip(gt.stamps_ns, pose_from_pq(gt.p_WS, gt.q_WS_wxyz)):
        poses.add(int(t), T)
    W0, H0 = cam.camera.size
    K = cam.camera.K.copy()
    K[0] *= width / W0
    K[1] *= height / H0
    mx, my = cam.camera.remap_to_pinhole(K, (width, height))
    stamps = depth.stamps_ns[::stride]
    if n > 0:
        stamps = stamps[:n]
    for st in stamps:
        d = cv2.remap(depth.read(st), mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan"))
        T_WS = poses.lookup(int(st), 1000, 50_000_000)
        if T_WS is None:
            continue
        yield int(st), d, K, T_WS @ cam.T_SC


def main(args: argparse.Namespace) -> int:
    sensor = SensorModelConfig(voxel_size_m=args.voxel, sigma_model="quadratic", k_sigma=args.sigma_k)
    mapper = SubmapMapper(sensor, SubmapConfig())
    frames = replica_frames(Path(args.replica), args.frames, args.stride) if args.replica else room_frames(args.frames or 60)
    from services.mapping.integrate import warm_up

    warm_up(sensor)  # compile/load the numba kernels outside the timing
    times, cpu, blocks = [], [], []
    for stamp, d, K, T_WC in frames:
        t0, c0 = time.perf_counter(), time.process_time()
        rep = mapper.integrate(d, None, K, T_WC, np.eye(4), stamp)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)  # all threads of this process: what it costs on an idle machine
        blocks.append(rep.result.n_voxel_blocks)
    t, c = 1e3 * np.array(times), 1e3 * np.array(cpu)
    t0 = time.perf_counter()
    mapper.remesh()
    mesh_s = time.perf_counter() - t0
    v, f = mapper.world_mesh()
    out = {"frames": len(times), "integrate_ms_p50": float(np.median(t)), "integrate_ms_p90": float(np.percentile(t, 90)),
           "integrate_ms_max": float(t.max()), "integrate_cpu_ms_p50": float(np.median(c)),
           "integrate_cpu_ms_p90": float(np.percentile(c, 90)), "load_avg_1min": os.getloadavg()[0], "voxel_blocks_per_frame_p50": float(np.median(blocks)),
           "submaps": len(mapper.submaps), "map_MB": mapper.nbytes() / 2**20,
           "submap_MB": [sm.store.nbytes() / 2**20 for sm in mapper.submaps], "full_mesh_s": mesh_s,
           "mesh_vertices": len(v), "mesh_faces": len(f)}
    print(f"integration per {512}x{384} frame at {args.voxel * 100:g} cm: median {out['integrate_ms_p50']:.1f} ms, "
          f"p90 {out['integrate_ms_p90']:.1f} ms over {len(t)} frames (CPU time, all threads: median "
          f"{out['integrate_cpu_ms_p50']:.1f} ms, p90 {out['integrate_cpu_ms_p90']:.1f} ms; load {out['load_avg_1min']:.1f} "
          f"on {os.cpu_count()} cores); {out['submaps']} submaps, "
          f"{out['map_MB']:.1f} MiB; full meshing {mesh_s:.2f} s", flush=True)
    if args.out:
        d = Path(args.out)
        write_ply(d / "mesh.ply", v, f)
        if args.eval and args.replica:
            from services.app.metrics.mesh import evaluate_mesh_files

            gt_mesh = Path(args.replica) / "mav0" / "scene" / "mesh.ply"
            if gt_mesh.is_file():
                res = evaluate_mesh_files(d / "mesh.ply", gt_mesh, out_dir=d)
                out["accuracy_m"], out["completeness"], out["completeness_5cm"] = res.accuracy_m, res.completeness, res.completeness_5cm
                print(f"mesh accuracy {res.accuracy_m:.4f} m, completeness {100 * res.completeness:.1f} % @ 0.2 m, "
                      f"{100 * res.completeness_5cm:.1f} % @ 0.05 m", flush=True)
        (d / "bench_mapping.json").write_text(json.dumps(out, indent=1))
    print(json.dumps(out), flush=True)
    return 0
