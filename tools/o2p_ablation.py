"""Ablation of the occupancy-to-point factors (paper Table IV), in one process, no transport.

    python -m tools.o2p_ablation DATASET [--seconds S] [--depth-every N] [--rows a,b,..] [--out DIR] [--set k=v]

Rows (each a full frontend + back end + depth + mapping run over the same frames):

* ``baseline``: no dense terms; the map is built from stereo-network depth at the estimated poses.
* ``heuristic``: frame-to-map and map-to-map factors on, stereo-network depth with a heuristic sigma
  (disparity sigma of ``--heuristic-px`` pixels: sigma_d = d^2 sigma_u / (f b)) for the factors and the map.
* ``learned``: as ``heuristic`` with the network's learned sigma.
* ``fused``: as ``learned``, but the map integrates the fused stereo + MVS depth (map-to-map points too).

Per row it prints the causal ATE [m] (SE(3) alignment), the mesh accuracy and completeness [m] against the
replica's scene mesh (tools/eval/mesh.py), the back end's per-frame wall time (median, p99) and the factor
counts. Stereo depth does not depend on the pose, so it is computed once and shared by the rows; MVS
(fused row) runs per row. Depth runs on every ``--depth-every``-th camera frame (the services run at
``depth.rate_hz``); the mapping waits for nothing here (the pose of a depth frame is the estimate just
produced for it). Short forms (``--seconds``) are for this shared 2-core machine.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from services.backend.service import BackendShell
from services.depth.pipeline import DepthPipeline
from services.frontend.service import FrontendShell
from services.mapping.export import field_message
from services.mapping.o2p_points import SubmapPointPool
from services.mapping.submaps import SubmapMapper
from services.system_config import load_system_config
from shared.euroc import read_trajectory
from shared.euroc_reader import EurocDataset
from shared.messages import ImuSample
from shared.rig import load_rig_config

ROWS = ("baseline", "heuristic", "learned", "fused")


def _frames(dataset: str, seconds: float):
    t0 = None
    for msg in EurocDataset(dataset).messages():
        t = int(msg.header.stamp_ns)
        t0 = t if t0 is None else t0
        if seconds > 0 and t - t0 > seconds * 1e9:
            return
        yield msg


_GT: dict = {}


def _gt_points(path: Path) -> np.ndarray:
    from tools.eval.mesh import load_points

    if path not in _GT:
        _GT[path] = load_points(path, 0.02)
    return _GT[path]


def run_row(row: str, dataset: str, overrides: list[str], seconds: float, depth_every: int, heuristic_px: float,
            stereo_cache: dict, mesh: bool = True) -> dict:
    cfg = load_system_config(None, overrides)
    if not cfg.rig.calibration:
        cfg.rig.calibration = dataset
    cams = load_rig_config(cfg.rig)
    fe, be = FrontendShell(cfg.frontend, cams), BackendShell(cfg.backend, cams)
    dense = row != "baseline"
    if dense:
        be.enable_o2p(dataclasses.replace(cfg.o2p, enabled=True))
    depth_cfg = dataclasses.replace(cfg.depth, use_mvs=(row == "fused"))
    by_name = {c.name: c for c in cams}
    pipe = DepthPipeline(depth_cfg, by_name[depth_cfg.left_camera], by_name[depth_cfg.right_camera])
    mapper = SubmapMapper(cfg.mapping.sensor, cfg.mapping.submaps)
    pool = SubmapPointPool(cfg.o2p.max_points_map)
    t_be, stamps, T_pub, n_frames, n_depth = [], [], [], 0, 0
    last_field_ns = 0
    for msg in _frames(dataset, seconds):
        if isinstance(msg, ImuSample):
            fe.gyro.add(int(msg.header.stamp_ns), msg.omega_S)
            be.add_imu(msg)
            continue
        n_frames += 1
        stamp = int(msg.header.stamp_ns)
        il, ir = msg.camera_names.index(depth_cfg.left_camera), msg.camera_names.index(depth_cfg.right_camera)
        pipe.remember_frame(stamp, msg.images[il])
        ff = fe.process(msg)
        if ff is None:
            continue
        t0 = time.perf_counter()
        out = be.process(ff)
        t_be.append(time.perf_counter() - t0)
        if out is None or out[0].status in ("initialising", "reset"):
            continue
        fe.gyro_bias = np.asarray(out[0].gyro_bias, float)
        stamps.append(stamp)
        T_pub.append(out[0].T_WS)
        if out[1] is not None:
            mapper.update_keyframes(out[1].ids, out[1].stamps_ns, out[1].T_WS)
            pipe.update_keyframes(out[1].stamps_ns, out[1].T_WS)
        if n_frames % depth_every:
            continue
        left, right = msg.images[il], msg.images[ir]
        if stamp not in stereo_cache:
            l_r, r_r = pipe.rect.rectify(left, right)
            stereo_cache[stamp] = pipe.stereo(l_r, r_r)
        d_s, s_s = stereo_cache[stamp]
        if row == "heuristic":
            s_s = (d_s**2 * heuristic_px / (pipe.f_px * pipe.baseline_m)).astype(np.float32)
        d_m, s_m = d_s, s_s
        T_WC = out[0].T_WS @ pipe.T_SC
        if row == "fused":
            mvs, _ = pipe.mvs(pipe.rect.rectify(left, right)[0], T_WC)
            if mvs is not None:
                from services.depth.uncertainty import fuse

                d_m, s_m = fuse(d_s, s_s, *mvs)
        n_depth += 1
        if dense:
            est = be.estimator  # as the service feeds depth/stereo
            be.o2p.add_depth(stamp, d_s, s_s, pipe.K, pipe.T_SC, out[0].T_WS, est.stamps, est.values)
        rep = mapper.integrate(d_m, s_m, pipe.K, T_WC, pipe.T_SC, stamp)
        sm = mapper.submaps[rep.submap_id]
        pool.add(rep.submap_id, d_m, s_m, pipe.K, np.linalg.inv(sm.T_WM) @ T_WC)
        if dense and rep.new_submap and rep.submap_id > 0:  # the closed submap: field, then its points
            old = mapper.submaps[rep.submap_id - 1]
            be.o2p.add_field(field_message(old, cfg.mapping.sensor.l_min))
            got = pool.pop(old.id)
            if got is not None:
                be.o2p.add_submap_points(old.id, *got)
        if dense and stamp - last_field_ns > cfg.mapping.field_period_s * 1e9:  # the growing submap, now and then
            last_field_ns = stamp
            be.o2p.add_field(field_message(sm, cfg.mapping.sensor.l_min))
    res = {"row": row, "frames": n_frames, "depth_frames": n_depth, "submaps": len(mapper.submaps),
           "backend_median_ms": 1e3 * float(np.median(t_be)), "backend_p99_ms": 1e3 * float(np.percentile(t_be, 99))}
    if dense:
        res["o2p_counts"] = dict(be.o2p.counts)
    ds = EurocDataset(dataset)
    align = None
    if ds.groundtruth_path is not None and len(stamps) >= 3:
        from tools.eval.ate import compute_ate

        gt = read_trajectory(ds.groundtruth_path)
        p = np.array(T_pub)[:, :3, 3]
        ate = compute_ate(gt.stamps_ns, gt.p_WS, np.array(stamps), p, mode="se3")
        res["ate_causal_m"], align = ate.rmse_m, ate.alignment
    scene = sorted(Path(dataset).glob("mav0/scene/*.ply"))
    if scene and mesh:
        from tools.eval.mesh import evaluate_points

        t0 = time.perf_counter()
        mapper.remesh(None)
        v, _ = mapper.world_mesh()
        if len(v) and align is not None:  # the estimate's W into the ground truth's frame (the trajectory's alignment)
            ev = evaluate_points(align.apply(np.asarray(v, float)), _gt_points(scene[0]))
            res["mesh_eval_s"] = round(time.perf_counter() - t0, 1)
            res.update({k: v_ for k, v_ in (ev if isinstance(ev, dict) else dataclasses.asdict(ev)).items()
                        if isinstance(v_, (int, float))})
    return res


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dataset")
    p.add_argument("--seconds", type=float, default=12.0, help="first S seconds of the sequence (0: all)")
    p.add_argument("--depth-every", type=int, default=4, help="depth on every N-th camera frame")
    p.add_argument("--rows", default=",".join(ROWS))
    p.add_argument("--heuristic-px", type=float, default=1.0, help="disparity sigma of the heuristic row [px]")
    p.add_argument("--set", action="append", default=[])
    p.add_argument("--no-mesh", action="store_true", help="skip the mesh evaluation (slow on a loaded CPU)")
    p.add_argument("--out")
    a = p.parse_args()
    cache: dict = {}
    results = []
    for row in a.rows.split(","):
        t0 = time.perf_counter()
        r = run_row(row, a.dataset, a.set, a.seconds, a.depth_every, a.heuristic_px, cache, not a.no_mesh)
        r["wall_s"] = round(time.perf_counter() - t0, 1)
        print(json.dumps(r, default=float), flush=True)
        results.append(r)
    if a.out:
        Path(a.out).mkdir(parents=True, exist_ok=True)
        (Path(a.out) / "o2p_ablation.json").write_text(json.dumps(results, indent=1, default=float))


if __name__ == "__main__":
    main()
