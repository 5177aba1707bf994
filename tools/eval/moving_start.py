"""Starts in mid-flight: the estimator switched on at several points of a replica, the error of its first seconds.

    python -m tools.eval.moving_start REPLICA [REPLICA ...] --starts 10,30,50 [--seconds 8] [--set KEY=VALUE]

For each replica and start S (seconds after its first frame) the frontend, fast path and back end run in process
(tools/vio/offline.run, deterministic: no loop closure, no occupancy terms) on the ``--seconds`` that follow S, as
if the sensors were switched on there (``player.start_s``). Printed per run: the causal ATE of those seconds under
their own SE(3) alignment, and of their first and last 2 s within it; then
the mean and the worst. A start in the middle of a run is what a back end restarted mid-flight meets
(docs/reliability.md), and what the MH sequences begin with.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from shared.euroc import read_trajectory
from shared.euroc_reader import EurocDataset
from shared.metrics.ate import compute_ate


def run_start(replica: str, start_s: float, seconds: float, overrides: list[str]) -> dict:
    """One run from ``start_s``: ATE of its ``seconds`` [m] (own SE(3) alignment), and of their first / last 2 s."""
    from tools.vio.offline import run

    res, traj = run(replica, None, [f"player.start_s={start_s}", *overrides], seconds=seconds)
    gt_path = EurocDataset(replica).groundtruth_path
    if gt_path is None or len(traj.stamps_ns) < 10:
        return {"replica": replica, "start_s": start_s, "poses": int(len(traj.stamps_ns)), "ate_m": None}
    gt = read_trajectory(gt_path)
    ate = compute_ate(gt.stamps_ns, gt.p_WS, traj.stamps_ns, traj.p_WS)
    t = (ate.stamps_ns - ate.stamps_ns[0]) * 1e-9
    rms = lambda e: float(np.sqrt(np.mean(e ** 2))) if len(e) else None  # noqa: E731
    return {"replica": replica, "start_s": start_s, "poses": int(len(traj.stamps_ns)), "ate_m": ate.rmse_m,
            "first2s_m": rms(ate.errors_m[t < 2.0]), "last2s_m": rms(ate.errors_m[t > t[-1] - 2.0])}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("replicas", nargs="+", help="replica folders (with ground truth)")
    p.add_argument("--starts", required=True, help="comma-separated start times after the first frame [s]")
    p.add_argument("--seconds", type=float, default=8.0, help="length of each run [s]")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")
    p.add_argument("--out", help="write the rows as JSON here")
    a = p.parse_args(argv)
    starts = [float(s) for s in a.starts.split(",") if s]
    rows = []
    for rep in a.replicas:
        for s in starts:
            r = run_start(rep, s, a.seconds, a.set)
            rows.append(r)
            f = lambda x: "-" if x is None else f"{x:.4f}"  # noqa: E731
            print(f"{Path(rep).name} start {s:6.1f} s: ATE {f(r['ate_m'])} m, first 2 s {f(r.get('first2s_m'))}, "
                  f"last 2 s {f(r.get('last2s_m'))} ({r['poses']} poses)", flush=True)
    ates = [r["ate_m"] for r in rows if r["ate_m"] is not None]
    if ates:
        print(f"[moving start] {len(ates)} runs of {a.seconds:.0f} s: mean ATE {np.mean(ates):.4f} m, worst "
              f"{np.max(ates):.4f} m", flush=True)
    if a.out:
        Path(a.out).write_text(json.dumps(rows, indent=1))
    return 0 if ates else 1


if __name__ == "__main__":
    raise SystemExit(main())
