"""What ``sigmaslam run`` does with the back end's final (non-causal) trajectory."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from shared.euroc import PoseSeries, write_euroc_csv, write_tum
from shared.geometry import R_to_quat_wxyz
from transport.queues import Empty


def wait_final(subscriber, timeout_s: float, stopped=lambda: False):
    """The first FinalTrajectory on ``subscriber`` within ``timeout_s`` (None if none came)."""
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end and not stopped():
        try:
            return subscriber.get(timeout=0.2)
        except Empty:
            continue
    return None


def final_series(msg) -> PoseSeries:
    T = np.asarray(msg.T_WS, float).reshape(-1, 4, 4)
    q = np.array([R_to_quat_wxyz(t[:3, :3]) for t in T]).reshape(-1, 4)
    return PoseSeries(np.asarray(msg.stamps_ns, np.int64), T[:, :3, 3], q)


def write_final(out: Path, msg) -> PoseSeries:
    """DIR/trajectory_final.txt (TUM) and .csv (EuRoC); DIR/trajectory.txt/.csv become the final one too."""
    traj = final_series(msg)
    for name in ("trajectory_final", "trajectory"):
        write_tum(out / f"{name}.txt", traj)
        write_euroc_csv(out / f"{name}.csv", traj)
    return traj


def loop_summary(msg) -> dict:
    return {"keyframes": int(msg.keyframes), "proposed": int(msg.loops_proposed), "verified": int(msg.loops_verified),
            "accepted": int(msg.loops_accepted), "relocalisations": int(msg.relocalisations)}
