"""Frontend + back end in one process on an EuRoC folder, no transport: for tuning and profiling.

    python -m tools.vio.offline DATASET [--max-frames N] [--set frontend.x=y] [--profile] [--out DIR]

(``--set player.start_s=S`` starts S seconds into the sequence: a start in mid-flight.)

Prints per-stage medians (wall and the CPU time of the running thread: on a shared machine the CPU time is the
steadier measure) and the causal ATE (SE(3)) when the folder has ground truth; ``--out`` writes the causal
trajectory (TUM). The services' own nodes on the in-process runner (services/app/inprocess.py), in the order of a
lockstep run; loop closure and occupancy terms off.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from services.app.system_config import load_system_config
from shared.euroc import series_from_matrices, read_trajectory, write_tum


def run(dataset: str, config: str | None, overrides: list[str], max_frames: int = 0, verbose: bool = False,
        seconds: float = 0.0, taps=()):
    """Frontend, fast path and back end (no loop closure, no occupancy terms) on the in-process runner (``seconds``
    > 0: the first that many; ``taps`` see every message, as run_in_process's). Per-frame cost: frontend + fast
    path (``sum_median_ms``); the back end's window optimisation runs at keyframes beside it."""
    from services.app.inprocess import run_in_process

    cfg = load_system_config(config, ["loop.enabled=false", "o2p.enabled=false", *overrides])
    run = run_in_process(dataset, cfg, max_frames, seconds=seconds, taps=taps)
    # the frontend process's frame handler holds the fast path, which it times on its own: frontend = the rest
    fp = run.nodes["frontend"].timer("fast_path")
    t_fp = np.array(list(zip(fp.durations_s, fp.cpu_s)) or [(np.nan, np.nan)])  # every frame with features
    t_fe = np.array(run.runner.times.get(("frontend", "on_frame"), [(np.nan, np.nan)]))
    if len(t_fe) == len(t_fp):
        t_fe = t_fe - t_fp
    kf = run.nodes["backend"].skipped_frames  # the back end's window optimisations: its calls less those it skipped
    t_be = np.array(run.runner.times.get(("backend", "on_features"), [(np.nan, np.nan)]))
    t_win = t_be[t_be[:, 1] > 1e-3] if (t_be[:, 1] > 1e-3).any() else t_be  # (skipped calls take microseconds)
    states = [s for s in run.states if s.status not in ("initialising", "reset")]
    if verbose:
        for k, st in enumerate(run.states):
            if k % 50 == 0:
                print(k, st.status, np.round(st.T_WS[:3, 3], 3), flush=True)
    stamps = np.array([s.header.stamp_ns for s in states], np.int64)
    traj = series_from_matrices(stamps, np.array([s.T_WS for s in states]))
    n = min(len(t_fe), len(t_fp))
    res = {"frames": run.frames, "poses": len(stamps), "frontend_median_ms": 1e3 * float(np.median(t_fe[:, 0])),
           "fast_path_median_ms": 1e3 * float(np.median(t_fp[:, 0])),
           "sum_median_ms": 1e3 * float(np.median(t_fe[:n, 0] + t_fp[:n, 0])),
           "cpu_frontend_median_ms": 1e3 * float(np.median(t_fe[:, 1])),
           "cpu_fast_path_median_ms": 1e3 * float(np.median(t_fp[:, 1])),
           "window_optimisations": len(t_be) - kf, "cpu_window_median_ms": 1e3 * float(np.median(t_win[:, 1])),
           "status": {k: sum(s.status == k for s in states) for k in ("tracking", "imu_only")}}
    if run.time_offset_ms is not None:  # backend.estimate_time_offset
        res["time_offset_ms"] = run.time_offset_ms
    if run.groundtruth_path is not None and len(stamps) >= 3:
        from shared.metrics.ate import compute_ate

        gt = read_trajectory(run.groundtruth_path)
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
