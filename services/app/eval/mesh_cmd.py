"""``sigmaslam eval mesh EST.ply GT.ply`` (or ``--est EST.ply --gt GT.ply``): the paper's mesh metrics
(services/app/metrics/mesh.py); ``--out DIR`` also writes the error-coloured mesh, a top view and the JSON."""

from __future__ import annotations

import argparse
import json
import sys


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("est_pos", nargs="?", metavar="EST.ply", help="estimated mesh (e.g. a run's mesh.ply)")
    p.add_argument("gt_pos", nargs="?", metavar="GT.ply", help="ground-truth mesh or point cloud")
    p.add_argument("--est", help="estimated mesh (instead of the first positional)")
    p.add_argument("--gt", help="ground truth (instead of the second positional)")
    p.add_argument("--voxel", type=float, default=0.01, help="downsampling voxel [m] (paper: 0.01)")
    p.add_argument("--no-icp", action="store_true", help="skip the point-to-plane ICP alignment")
    p.add_argument("--out", metavar="DIR", help="write error_mesh.ply, error_top.png and mesh_eval.json here")


def main(args: argparse.Namespace) -> int:
    from services.app.metrics.mesh import evaluate_mesh_files

    est, gt = args.est or args.est_pos, args.gt or args.gt_pos
    if not est or not gt:
        print("sigmaslam eval mesh: need EST.ply and GT.ply", file=sys.stderr)
        return 2
    try:
        res = evaluate_mesh_files(est, gt, voxel_m=args.voxel, icp=not args.no_icp, out_dir=args.out)
    except (FileNotFoundError, ValueError) as exc:
        print(f"sigmaslam eval mesh: {exc}", file=sys.stderr)
        return 1
    print(f"accuracy {res.accuracy_m:.4f} m (median {res.accuracy_median_m:.4f})  completeness "
          f"{100 * res.completeness:.2f} % @ {res.completeness_threshold_m:.2f} m, {100 * res.completeness_5cm:.2f} % @ 0.05 m  "
          f"(est {res.n_est}, gt {res.n_gt} points, ICP fitness {res.icp_fitness:.3f})", flush=True)
    if args.out:
        print(json.dumps({"written": args.out}), flush=True)
    return 0
