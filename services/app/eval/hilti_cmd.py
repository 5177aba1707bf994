"""``sigmaslam eval hilti --est EST (--dataset DIR | --control CSV)``: Hilti 2022 score (services/app/metrics/hilti.py).

Control points: ``--control`` a CSV of ``stamp_ns,x,y,z`` rows [ns, m] (a header line starting with '#' is
skipped), or ``--dataset`` a replica/EuRoC folder whose ground truth gives ``--points`` control points at camera
frame times. The estimate is a TUM or EuRoC CSV trajectory (e.g. a run's trajectory_causal.txt or
trajectory_final.txt).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def add_arguments(a: argparse.ArgumentParser) -> None:
    a.add_argument("--est", required=True, help="estimate (TUM or EuRoC CSV)")
    src = a.add_mutually_exclusive_group(required=True)
    src.add_argument("--dataset", help="EuRoC/replica folder: control points sampled from its ground truth")
    src.add_argument("--control", help="control points CSV: stamp_ns,x,y,z [ns, m]")
    a.add_argument("--points", type=int, default=12, help="control points sampled from the ground truth")
    a.add_argument("--max-dt-s", type=float, default=2.0, help="largest time difference of an association [s]")
    a.add_argument("--json", action="store_true", help="print the result as JSON")


def dataset_control_points(dataset: Path, n: int) -> tuple[np.ndarray, np.ndarray]:
    from shared.euroc import read_trajectory
    from services.app.metrics.hilti import control_points_from_groundtruth

    root = dataset / "mav0" if (dataset / "mav0").is_dir() else dataset
    gt_path, cam_csv = root / "state_groundtruth_estimate0" / "data.csv", root / "cam0" / "data.csv"
    if not gt_path.is_file() or not cam_csv.is_file():
        raise ValueError(f"{dataset}: needs state_groundtruth_estimate0/data.csv and cam0/data.csv")
    gt = read_trajectory(gt_path)
    frames = np.loadtxt(cam_csv, delimiter=",", usecols=0, dtype=np.int64, comments="#", ndmin=1)
    return control_points_from_groundtruth(gt.stamps_ns, gt.p_WS, frames, n)


def read_control_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    try:
        rows = np.loadtxt(path, delimiter=",", comments="#", ndmin=2, dtype=float)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: not a stamp_ns,x,y,z CSV: {exc}") from exc
    if rows.shape[1] != 4 or len(rows) == 0:
        raise ValueError(f"{path}: expected rows of stamp_ns,x,y,z, got shape {rows.shape}")
    stamps = np.array([int(line.split(",")[0]) for line in Path(path).read_text().splitlines()
                       if line.strip() and not line.lstrip().startswith("#")], np.int64)  # exact int64 stamps
    return stamps, rows[:, 1:4]


def main(args: argparse.Namespace) -> int:
    from shared.euroc import TrajectoryFileError, read_trajectory
    from services.app.metrics.hilti import hilti_score

    try:
        if args.dataset:
            cs, cp = dataset_control_points(Path(args.dataset), args.points)
        else:
            cs, cp = read_control_csv(Path(args.control))
        est = read_trajectory(args.est)
        res = hilti_score(cs, cp, est.stamps_ns, est.p_WS, int(args.max_dt_s * 1e9))
    except (TrajectoryFileError, ValueError, OSError) as exc:
        print(f"sigmaslam eval hilti: {exc}")
        return 1
    if args.json:
        print(json.dumps(res.summary()))
    else:
        errs = ", ".join("-" if not np.isfinite(e) else f"{e * 100:.1f}" for e in res.errors_m)
        print(f"Hilti score {res.score:.2f} / 100 ({res.points} points, {res.n_associated}/{res.n_control} control "
              f"points associated); errors [cm]: {errs}")
    return 0
