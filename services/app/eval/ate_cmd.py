"""``sigmaslam eval ate --gt GT --est EST``: ATE RMSE after alignment (shared/metrics/ate.py).

Reads TUM or EuRoC CSV (ground truth or pose files, .xz too). Alignment: ``se3`` (default, the paper's),
``sim3``, ``posyaw`` or ``none``; ``--align-first-s S`` fits the alignment on the first S seconds only.
"""

from __future__ import annotations

import argparse
import json


def add_arguments(a: argparse.ArgumentParser) -> None:
    a.add_argument("--gt", required=True, help="ground truth (EuRoC CSV or TUM)")
    a.add_argument("--est", required=True, help="estimate (TUM or EuRoC CSV)")
    a.add_argument("--mode", default="se3", choices=("se3", "sim3", "posyaw", "none"), help="alignment")
    a.add_argument("--align-first-s", type=float, default=None, help="align on the first seconds only [s]")
    a.add_argument("--max-diff-ms", type=float, default=10.0, help="largest time difference of a matched pair [ms]")
    a.add_argument("--json", action="store_true", help="print the result as JSON")


def main(args: argparse.Namespace) -> int:
    from shared.euroc import TrajectoryFileError, read_trajectory
    from shared.metrics.ate import compute_ate

    try:
        gt, est = read_trajectory(args.gt), read_trajectory(args.est)
        res = compute_ate(gt.stamps_ns, gt.p_WS, est.stamps_ns, est.p_WS, mode=args.mode,
                          align_first_s=args.align_first_s, max_diff_ns=int(args.max_diff_ms * 1e6))
    except (TrajectoryFileError, ValueError) as exc:
        print(f"sigmaslam eval ate: {exc}")
        return 1
    out = {"ate_rmse_m": res.rmse_m, "mean_m": res.mean_m, "median_m": res.median_m, "max_m": res.max_m,
           "matched": res.matched, "mode": args.mode, "scale": res.alignment.scale}
    if args.json:
        print(json.dumps(out))
    else:
        print(f"ATE ({args.mode}) RMSE {res.rmse_m:.4f} m, mean {res.mean_m:.4f}, median {res.median_m:.4f}, "
              f"max {res.max_m:.4f} m over {res.matched} poses"
              + (f", scale {res.alignment.scale:.4f}" if args.mode == "sim3" else ""))
    return 0
