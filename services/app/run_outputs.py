"""What ``sigmaslam run`` writes: the causal trajectory of the states it collected (in the frame they are in), the back
end's final (non-causal) trajectory, its refined extrinsics, the run's stats (stats.json) and ATE (ate.json)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from services.app.metrics.latency import first_arrivals, matched_latencies, sent_latencies, summary
from shared.euroc import PoseSeries, read_trajectory, series_from_matrices, write_euroc_csv, write_tum
from shared.map_folder import UNALIGNED_FRAME


# per-frame stages whose medians add up to the estimator's cost per camera frame: the frontend process's tracking
# and fast path (the back end's window optimisation runs beside them, at keyframes: reported on its own)
FRAME_STAGES = (("frontend", "track"),)

# where a dataset folder (the one holding mav0/, or mav0 itself) keeps its ground truth, in the order looked for:
# the ASL layout's own file, then a TUM or CSV file at the folder's top (what trimmed or converted folders carry)
GT_CANDIDATES = ("mav0/state_groundtruth_estimate0/data.csv", "groundtruth_tum.txt", "groundtruth.txt",
                 "groundtruth.csv")


def final_series(msg) -> PoseSeries:
    return series_from_matrices(msg.stamps_ns, msg.T_WS)


def frame_comment(frame_id: str, saved_map: bool) -> str:
    """The header line of a trajectory file naming the frame of its poses (a run's world frame 'W', which with a
    saved map is the map's, or a run's own frame 'odom' before it relocalised in a saved map)."""
    if frame_id == UNALIGNED_FRAME:
        return (f"frame: {UNALIGNED_FRAME} (this run's own frame, its first pose's: it never relocalised in the saved "
                "map)")
    return "frame: W (the saved map's world frame)" if saved_map else "frame: W (this run's world frame)"


def write_final(out: Path, msg, saved_map: bool = False) -> PoseSeries:
    """DIR/trajectory_final.txt (TUM) and .csv (EuRoC); DIR/trajectory.txt/.csv become the final one too. The header
    names the frame (:func:`frame_comment`)."""
    traj = final_series(msg)
    comment = frame_comment(msg.header.frame_id, saved_map)
    for name in ("trajectory_final", "trajectory"):
        write_tum(out / f"{name}.txt", traj, comment)
        write_euroc_csv(out / f"{name}.csv", traj, comment)
    return traj


def loop_summary(msg) -> dict:
    return {"keyframes": int(msg.keyframes), "proposed": int(msg.loops_proposed), "verified": int(msg.loops_verified),
            "accepted": int(msg.loops_accepted), "relocalisations": int(msg.relocalisations)}


def write_refined_extrinsics(out: Path, rig_cfg, T_SC: np.ndarray) -> list[dict]:
    """DIR/extrinsics_refined.yaml: the rig of ``rig_cfg`` with the back end's refined ``T_SC`` (C,4,4), a rig YAML
    that ``rig.calibration`` reads; prints and returns each camera's change from the calibration."""
    from shared.camera import write_rig_yaml
    from shared.geometry import pose_error
    from shared.rig import load_rig_config

    cams = load_rig_config(rig_cfg)
    if len(cams) != len(T_SC):
        print(f"[sigmaslam run] refined extrinsics of {len(T_SC)} cameras for a rig of {len(cams)}: not written",
              flush=True)
        return []
    refined = [dataclasses.replace(c, T_SC=T) for c, T in zip(cams, T_SC)]
    path = write_rig_yaml(out / "extrinsics_refined.yaml", refined,
                          f"{rig_cfg.calibration or 'the default rig'} with each T_SC refined online by sigmaslam run")
    changes = []
    for c, T in zip(cams, T_SC):
        dt, dr = pose_error(c.T_SC, T)
        changes.append({"camera": c.name, "rotation_deg": float(np.degrees(dr)), "translation_m": float(dt)})
    print(f"[sigmaslam run] refined extrinsics in {path}: " + ", ".join(
        f"{d['camera']} moved {d['rotation_deg']:.2f} deg, {1e3 * d['translation_m']:.1f} mm" for d in changes),
        flush=True)
    return changes


def causal_trajectory(states) -> tuple[PoseSeries, str]:
    """The causal trajectory to write and its frame. No pose in 'initialising' and 'reset'. A run localising in a
    saved map publishes in its own frame (:data:`UNALIGNED_FRAME`) until it relocalises and in the map's ('W') from
    then on: the trajectory is its states in the map's frame, or, when it never relocalised, all its states in its
    own frame, so that no run loses its trajectory."""
    posed = [s for s in states if s.status not in ("initialising", "reset")]
    good, frame = [s for s in posed if s.header.frame_id != UNALIGNED_FRAME], "W"
    if not good and posed:
        good, frame = posed, UNALIGNED_FRAME
    stamps = np.array([s.header.stamp_ns for s in good], np.int64)
    order = np.argsort(stamps, kind="stable")
    T = np.array([s.T_WS for s in good]).reshape(-1, 4, 4)[order]
    return series_from_matrices(stamps[order], T), frame


def stats_summary(col) -> dict:
    """stats.json of a run's :class:`services.app.run_collector.Collection`."""
    out: dict = {"services": {}}
    for name, s in col.stats.items():
        stages = {}
        for k, st in enumerate(s.stage_names):
            w = col.window_p50.get((name, st), [])
            stages[st] = {"count": int(s.stage_count[k]), "overruns": int(s.stage_overruns[k]),
                          "budget_ms": float(s.stage_budget_ms[k]), "last_window_p50_ms": float(s.stage_p50_ms[k]),
                          "last_window_p99_ms": float(s.stage_p99_ms[k]),
                          "median_of_window_p50_ms": float(np.median(w)) if w else float("nan")}
        queues = {q: {"received": int(s.queue_received[k]), "dropped": int(s.queue_dropped[k])}
                  for k, q in enumerate(s.queue_names)}
        out["services"][name] = {"uptime_s": float(s.uptime_s), "rss_mb": float(s.rss_mb), "stages": stages,
                                 "queues": queues,
                                 "counters": {c: int(v) for c, v in zip(s.counter_names, s.counter_values)}}
    per_frame = [out["services"].get(svc, {}).get("stages", {}).get(st, {}).get("median_of_window_p50_ms")
                 for svc, st in FRAME_STAGES]
    out["frontend_backend_median_ms"] = float(sum(per_frame)) if all(v is not None for v in per_frame) else None
    status = [s.status for s in col.states]
    out["states"] = {k: status.count(k) for k in sorted(set(status))}
    out["frames_sent"] = int(col.end.frames_sent) if col.end is not None else None
    # sensor publication -> estimator/state per frame, from the publishers' send times (services/app/metrics/latency.py);
    # the arrival times at this process, which runs behind the path to a pose and sees frames late, only where the
    # samples carried none
    published = first_arrivals(*col.arrivals.get("frame"))
    arrived = summary(matched_latencies(published, *col.arrivals.get("state"))["latency_ms"])
    sent = summary(sent_latencies(col.arrivals, "state")["latency_ms"])
    out["state_latency_ms"] = sent if sent.get("n") else arrived
    out["state_latency_from"] = "send times" if sent.get("n") else "arrival times"
    out["state_latency_arrival_ms"] = arrived
    answered = {int(s.header.stamp_ns) for s in col.states}  # any status: the estimator answered the frame
    out["frames_without_state"] = (None if out["frames_sent"] is None
                                   else max(0, out["frames_sent"] - len(answered)))
    out["drops"] = {f"{svc}:{q}": v["dropped"] for svc, d in out["services"].items()
                    for q, v in d["queues"].items() if v["dropped"]}
    px = out["services"].get("depth", {}).get("counters", {})
    n_px = px.get("confident_pixels", 0) + px.get("uncertain_pixels", 0)
    out["depth_uncertain_fraction"] = px.get("uncertain_pixels", 0) / n_px if n_px else None
    out["localisation"] = localisation_summary(col.states)
    return out


def localisation_summary(states) -> dict | None:
    """How a run localising in a saved map got there: states before and after its relocalisation, and the sensor
    time from the first state to the first one in the map's frame (None for a run without a saved map)."""
    posed = [s for s in states if s.status not in ("initialising", "reset")]
    before = sum(s.header.frame_id == UNALIGNED_FRAME for s in posed)
    if not before:
        return None
    in_map = [s for s in posed if s.header.frame_id != UNALIGNED_FRAME]
    first = int(states[0].header.stamp_ns)
    return {"states_before_relocalisation": before, "states_in_map_frame": len(in_map),
            "time_to_relocalise_s": (int(in_map[0].header.stamp_ns) - first) * 1e-9 if in_map else None}


def find_ground_truth(dataset: Path) -> Path | None:
    """The first of :data:`GT_CANDIDATES` in ``dataset`` (the folder holding mav0/, or mav0 itself), or None."""
    root = dataset / "mav0" if (dataset / "mav0").is_dir() else dataset  # the reader's root (mav0 or its content)
    base = root.parent if root.name == "mav0" else root
    paths = [root / "state_groundtruth_estimate0" / "data.csv", *(base / c for c in GT_CANDIDATES[1:])]
    return next((q for q in paths if q.is_file()), None)


def evaluate(traj: PoseSeries, gt_path: Path) -> dict:
    """SE(3)-aligned ATE of ``traj`` over its poses that have a ground-truth pose within 10 ms (the overlap)."""
    from shared.metrics.ate import compute_ate

    gt = read_trajectory(gt_path)
    res = compute_ate(gt.stamps_ns, gt.p_WS, traj.stamps_ns, traj.p_WS, mode="se3")
    return {"ate_rmse_m": res.rmse_m, "ate_mean_m": res.mean_m, "ate_median_m": res.median_m,
            "ate_max_m": res.max_m, "matched": res.matched, "poses": len(traj.stamps_ns),
            "matched_span_ns": [int(res.stamps_ns[0]), int(res.stamps_ns[-1])],
            "groundtruth_span_ns": [int(gt.stamps_ns[0]), int(gt.stamps_ns[-1])],
            "alignment": "se3", "groundtruth": str(gt_path)}


def ate_line(kind: str, ate: dict) -> str:
    t0, t1 = ate["matched_span_ns"]
    return (f"[sigmaslam run] {kind} ATE (SE(3)) RMSE {ate['ate_rmse_m']:.4f} m over {ate['matched']} of "
            f"{ate['poses']} poses ({(t1 - t0) * 1e-9:.1f} s with ground truth)")


def write_ate(out: Path, traj: PoseSeries, final_traj: PoseSeries | None, gt: Path) -> dict:
    """DIR/ate.json (causal, and non-causal when there is a final trajectory) and their printed lines; returns what
    ate.json holds."""
    ate = evaluate(traj, gt)
    (out / "ate.json").write_text(json.dumps(ate, indent=2))
    print(ate_line("causal", ate), flush=True)
    if final_traj is not None and len(final_traj.stamps_ns) >= 3:
        ate["non_causal"] = evaluate(final_traj, gt)
        (out / "ate.json").write_text(json.dumps(ate, indent=2))
        print(ate_line("non-causal", ate["non_causal"]), flush=True)
    return ate


def write_occupancy_voxels(out: Path, query_cfg=None) -> dict | None:
    """DIR/occupancy_voxels.npz and DIR/occupied_voxels.ply of the run's saved map (DIR/map/dense.npz), written after
    the pipeline (services/mapping/voxel_export.py); None when the run saved no dense map."""
    import time

    from services.mapping.combined import CombinedMap
    from services.mapping.io import MapFileError, load_map
    from services.mapping.voxel_export import write_voxels
    from shared.map_folder import dense_path

    path = dense_path(out)
    if not path.is_file():
        return None
    t0 = time.monotonic()
    try:
        npz, ply, n = write_voxels(CombinedMap.of(load_map(path), query_cfg), out)
    except MapFileError as exc:
        print(f"[sigmaslam run] no occupancy voxels: {exc}", flush=True)
        return None
    print(f"[sigmaslam run] wrote {npz.name} ({n['occupied']} occupied, {n['free']} free voxels) and {ply.name} "
          f"({time.monotonic() - t0:.1f} s)", flush=True)
    return n
