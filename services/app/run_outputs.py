"""What ``sigmaslam run`` does with the back end's final (non-causal) trajectory and its refined extrinsics."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from shared.euroc import series_from_matrices, PoseSeries, write_euroc_csv, write_tum
from shared.map_folder import UNALIGNED_FRAME
from transport.queues import Empty


def wait_final(subscriber, timeout_s: float, stopped=lambda: False, report_every_s: float = 10.0):
    """The first FinalTrajectory on ``subscriber`` within ``timeout_s`` (None if none came); says every
    ``report_every_s`` that it is still waiting."""
    t0 = time.monotonic()
    t_end, next_report = t0 + timeout_s, t0 + report_every_s
    while time.monotonic() < t_end and not stopped():
        if time.monotonic() >= next_report:
            print(f"[sigmaslam run] still waiting for the final bundle adjustment ({time.monotonic() - t0:.0f} s)",
                  flush=True)
            next_report += report_every_s
        try:
            return subscriber.get(timeout=0.2)
        except Empty:
            continue
    return None


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
