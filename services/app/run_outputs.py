"""What ``sigmaslam run`` does with the back end's final (non-causal) trajectory."""

from __future__ import annotations

import time
from pathlib import Path


from shared.euroc import series_from_matrices, PoseSeries, write_euroc_csv, write_tum
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
