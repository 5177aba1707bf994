"""Frontend + back end in one process on an EuRoC folder, no transport: for tuning and profiling.

    python -m tools.vio.offline DATASET [--max-frames N] [--set frontend.x=y] [--profile] [--out DIR]

Prints per-stage medians (wall and the process CPU time, all threads: on a shared machine the CPU time is the steadier
measure) and the causal ATE (SE(3)) when the folder has ground truth; ``--out`` writes the
causal trajectory (TUM). The same algorithms and config as the services, fed in the same order.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from services.backend.service import BackendShell
from services.frontend.service import FrontendShell
from services.system_config import load_system_config
from shared.euroc import series_from_matrices, read_trajectory, write_tum
from shared.euroc_reader import EurocDataset
from shared.messages import ImuSample
from shared.rig import load_rig_config


def run(dataset: str, config: str | None, overrides: list[str], max_frames: int = 0, verbose: bool = False):
    cfg = load_system_config(config, overrides)
    if not cfg.rig.calibration:
        cfg.rig.calibration = dataset
    cams = load_rig_config(cfg.rig)
    fe, be = FrontendShell(cfg.frontend, cams), BackendShell(cfg.backend, cams)
    ds = EurocDataset(dataset)
    t_fe, t_be, states, cpu = [], [], [], []
    frames = 0
    for msg in ds.messages():
        if isinstance(msg, ImuSample):
            fe.gyro.add(int(msg.header.stamp_ns), msg.omega_S)
            be.add_imu(msg)
            continue
        if max_frames and frames >= max_frames:
            break
        frames += 1
        t0, c0 = time.perf_counter(), time.process_time()
        ff = fe.process(msg)
        t1, c1 = time.perf_counter(), time.process_time()
        out = be.process(ff) if ff is not None else None
        t2, c2 = time.perf_counter(), time.process_time()
        t_fe.append(t1 - t0)
        t_be.append(t2 - t1)
        cpu.append((c1 - c0, c2 - c1))
        if out is not None:
            st = out[0]
            fe.gyro_bias = np.asarray(st.gyro_bias, float)
            if st.status != "initialising":
                states.append(st)
            if verbose and frames % 50 == 0:
                print(frames, st.status, np.round(st.T_WS[:3, 3], 3), f"fe {1e3 * (t1 - t0):.1f} be {1e3 * (t2 - t1):.1f} ms",
                      be.estimator.window_counts(), flush=True)
    stamps = np.array([s.header.stamp_ns for s in states], np.int64)
    traj = series_from_matrices(stamps, np.array([s.T_WS for s in states]))
    res = {"frames": frames, "poses": len(stamps), "frontend_median_ms": 1e3 * float(np.median(t_fe)),
           "backend_median_ms": 1e3 * float(np.median(t_be)),
           "sum_median_ms": 1e3 * float(np.median(np.array(t_fe) + np.array(t_be))),
           "cpu_frontend_median_ms": 1e3 * float(np.median([c[0] for c in cpu])),
           "cpu_backend_median_ms": 1e3 * float(np.median([c[1] for c in cpu])),
           "status": {k: sum(s.status == k for s in states) for k in ("tracking", "imu_only")}}
    if ds.groundtruth_path is not None and len(stamps) >= 3:
        from shared.metrics.ate import compute_ate

        gt = read_trajectory(ds.groundtruth_path)
        res["ate_rmse_m"] = compute_ate(gt.stamps_ns, gt.p_WS, stamps, traj.p_WS, mode="se3").rmse_m
    return res, traj


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dataset")
    p.add_argument("config", nargs="?")
    p.add_argument("--set", action="append", default=[])
    p.add_argument("--max-frames", type=int, default=0)
    p.add_argument("--profile", action="store_true")
    p.add_argument("--out")
    p.add_argument("-v", "--verbose", action="store_true")
    a = p.parse_args()
    if a.profile:
        import cProfile
        import pstats

        prof = cProfile.Profile()
        prof.enable()
    res, traj = run(a.dataset, a.config, a.set, a.max_frames, a.verbose)
    if a.profile:
        prof.disable()
        pstats.Stats(prof).sort_stats("tottime").print_stats(25)
    print(res, flush=True)
    if a.out:
        Path(a.out).mkdir(parents=True, exist_ok=True)
        write_tum(Path(a.out) / "trajectory_causal.txt", traj)


if __name__ == "__main__":
    main()
