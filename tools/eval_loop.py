"""Loop closure and the final bundle adjustment on an EuRoC folder, in one process, no transport.

    python -m tools.eval_loop DATASET [--max-frames N] [--set loop.x=y] [--no-loop] [--out DIR]

Frontend + back end (the services' shells) with :class:`services.backend.loop.backend_loop.LoopClosingBackend` fed in
the services' order (keyframe descriptors before their frame). Prints the causal ATE of the raw window
estimate and of the published (pose-graph corrected) poses, the non-causal ATE after the final BA, loop
counts, and the back end's per-frame time (median, p99; wall and this thread's CPU) with the loop thread running. ``--out`` writes
trajectory_causal.txt and trajectory_final.txt (TUM) and eval_loop.json.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from services.backend.service import BackendShell
from services.frontend.service import FrontendShell
from services.backend.loop.backend_loop import LoopClosingBackend
from services.frontend.keyframe_features import keyframe_features_message
from services.system_config import load_system_config
from shared.euroc import series_from_matrices, read_trajectory, write_tum
from shared.euroc_reader import EurocDataset
from shared.messages import ImuSample


def run(dataset: str, overrides: list[str], max_frames: int = 0, loop: bool = True) -> tuple[dict, dict]:
    cfg = load_system_config(None, overrides)
    if not cfg.rig.calibration:
        cfg.rig.calibration = dataset
    from shared.rig import load_rig_config

    cams = load_rig_config(cfg.rig)
    fe, be = FrontendShell(cfg.frontend, cams), BackendShell(cfg.backend, cams)
    lb = LoopClosingBackend(be, cfg.loop) if loop else None
    ds = EurocDataset(dataset)
    t_be, c_be, stamps, T_pub, frames = [], [], [], [], 0
    for msg in ds.messages():
        if isinstance(msg, ImuSample):
            fe.gyro.add(int(msg.header.stamp_ns), msg.omega_S)
            be.add_imu(msg)
            continue
        if max_frames and frames >= max_frames:
            break
        frames += 1
        ff = fe.process(msg)
        if ff is None:
            continue
        if lb is not None and ff.is_keyframe:
            kff = keyframe_features_message(fe.tracker, ff.header.stamp_ns)
            if kff is not None:
                lb.add_keyframe_features(kff)
        t0, c0 = time.perf_counter(), time.thread_time()
        out = be.process(ff) if lb is None else lb.process(ff)
        t_be.append(time.perf_counter() - t0)
        c_be.append(time.thread_time() - c0)
        if out is None:
            continue
        fe.gyro_bias = np.asarray(out[0].gyro_bias, float)
        if out[0].status != "initialising":
            stamps.append(out[0].header.stamp_ns)
            T_pub.append(out[0].T_WS)
    res = {"frames": frames, "backend_median_ms": 1e3 * float(np.median(t_be)),
           "backend_p99_ms": 1e3 * float(np.percentile(t_be, 99)),
           "backend_cpu_median_ms": 1e3 * float(np.median(c_be)), "backend_cpu_p99_ms": 1e3 * float(np.percentile(c_be, 99)),
           "loop": loop}
    trajs = {"causal": series_from_matrices(stamps, T_pub)}
    if lb is not None:
        t0 = time.perf_counter()
        final = lb.finish()
        res["final_ba_s"] = time.perf_counter() - t0
        res["loops"] = lb.counts
        res["pose_graph_solve_ms"] = [round(x, 1) for x in lb.runner.closer.solve_ms]
        trajs["raw"] = series_from_matrices(lb._stamps, lb._T_raw)
        if final is not None:
            trajs["final"] = series_from_matrices(final.stamps_ns, final.T_WS)
            res["final_keyframes"] = final.keyframes
        lb.close()
    if ds.groundtruth_path is not None:
        from shared.metrics.ate import compute_ate

        gt = read_trajectory(ds.groundtruth_path)
        for k, tr in trajs.items():
            if len(tr.stamps_ns) >= 3:
                res[f"ate_{k}_m"] = compute_ate(gt.stamps_ns, gt.p_WS, tr.stamps_ns, tr.p_WS, mode="se3").rmse_m
    return res, trajs


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dataset")
    p.add_argument("--set", action="append", default=[])
    p.add_argument("--max-frames", type=int, default=0)
    p.add_argument("--no-loop", action="store_true")
    p.add_argument("--out")
    a = p.parse_args()
    res, trajs = run(a.dataset, a.set, a.max_frames, not a.no_loop)
    print(json.dumps(res, indent=1, default=str), flush=True)
    if a.out:
        out = Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        write_tum(out / "trajectory_causal.txt", trajs["causal"])
        if "final" in trajs:
            write_tum(out / "trajectory_final.txt", trajs["final"])
        (out / "eval_loop.json").write_text(json.dumps(res, indent=1, default=str))


if __name__ == "__main__":
    main()
