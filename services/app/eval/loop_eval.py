"""Loop closure and the final bundle adjustment on an EuRoC folder, in one process, no transport: the pipeline's own
nodes on the in-process runner (services/app/inprocess.py), in the order of a lockstep run. ``sigmaslam eval suite
--in-process`` scores it; ``python -m tools.eval_loop`` prints it.

:func:`evaluate_loop` gives the causal ATE of the raw window estimate and of the published (pose-graph corrected)
poses, the non-causal ATE after the final BA, loop counts, and the back end's per-frame time (median, p99; wall and
this thread's CPU) with the loop closer working inside the frame's call (``loop.synchronous``)."""

from __future__ import annotations

import numpy as np

from services.app.inprocess import run_in_process
from services.app.system_config import load_system_config
from shared import topics
from shared.euroc import read_trajectory, series_from_matrices


def evaluate_loop(dataset: str, overrides: list[str], max_frames: int = 0, loop: bool = True,
                  config: str | None = None) -> tuple[dict, dict]:
    """Frontend and back end (loop closure as ``loop`` says, no occupancy terms) on the in-process runner, with
    the system config ``config`` (YAML; default the built-in defaults) and ``overrides``."""
    cfg = load_system_config(config, ["o2p.enabled=false", *overrides, f"loop.enabled={str(loop).lower()}"])
    raw: list = []  # the published states without the loop correction the fast path applied (its latest window's)
    T_corr = [np.eye(4)]

    def uncorrected(topic, msg) -> None:
        if topic == topics.WINDOW and msg.status not in ("initialising",):
            T_corr[0] = np.asarray(msg.T_corr)
        elif topic == topics.STATE and msg.status not in ("initialising", "reset"):
            raw.append((msg.header.stamp_ns, np.linalg.inv(T_corr[0]) @ msg.T_WS))

    run = run_in_process(dataset, cfg, max_frames, taps=[uncorrected])
    times = np.array(run.runner.times.get(("backend", "on_features"), [(np.nan, np.nan)]))
    t_be, c_be = times[:, 0], times[:, 1]
    published = [s for s in run.states if s.status not in ("initialising", "reset")]
    res = {"frames": run.frames, "backend_median_ms": 1e3 * float(np.median(t_be)),
           "backend_p99_ms": 1e3 * float(np.percentile(t_be, 99)),
           "backend_cpu_median_ms": 1e3 * float(np.median(c_be)), "backend_cpu_p99_ms": 1e3 * float(np.percentile(c_be, 99)),
           "loop": loop}
    if run.time_offset_ms is not None:  # backend.estimate_time_offset
        res["time_offset_ms"] = run.time_offset_ms
    trajs = {"causal": series_from_matrices([s.header.stamp_ns for s in published], [s.T_WS for s in published])}
    lb = run.nodes["backend"].loop_closure
    if lb is not None:
        res["final_ba_s"] = float(sum(t for t, _ in run.runner.times.get(("backend", "on_stream_end"), [])))
        res["loops"] = lb.counts
        res["pose_graph_solve_ms"] = [round(x, 1) for x in lb.runner.closer.solve_ms]
        delays = lb.runner.closer.loop_delays_s  # query keyframe -> its factor in the pose graph, sensor time
        res["loop_delay_median_s"] = float(np.median(delays)) if delays else None
        trajs["raw"] = series_from_matrices([s for s, _ in raw], [T for _, T in raw])
        if run.final is not None:
            trajs["final"] = series_from_matrices(run.final.stamps_ns, run.final.T_WS)
            res["final_keyframes"] = run.final.keyframes
    if run.groundtruth_path is not None:
        from shared.metrics.ate import compute_ate
        from services.app.metrics.segments import segment_errors

        gt = read_trajectory(run.groundtruth_path)
        for k, tr in trajs.items():
            if len(tr.stamps_ns) >= 3:
                ate = compute_ate(gt.stamps_ns, gt.p_WS, tr.stamps_ns, tr.p_WS, mode="se3")
                res[f"ate_{k}_m"] = ate.rmse_m
                seg = segment_errors(ate, gt.stamps_ns, gt.q_WS_wxyz)
                res[f"ate_{k}_first10s_m"], res[f"ate_{k}_fastest10s_m"] = seg["first_rmse_m"], seg["fastest_rmse_m"]
                res["fastest10s"] = {"start_s": round(seg["fastest_start_s"], 1),
                                     "deg_s": round(seg["fastest_deg_s"], 1)}
    return res, trajs
