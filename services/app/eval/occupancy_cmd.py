"""``sigmaslam eval occupancy RUN_DIR --replica R``: is the run's free space safe? False free and free recall of the
combined map's voxels (and of each submap alone) and of its 2D grid, measured against the replica's exact scene mesh
(services/app/metrics/occupancy.py); printed, and written to ``RUN_DIR/occupancy_eval.json``."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_dir", help="a run's output folder (map/dense.npz, trajectory files, occupancy_grid.yaml)")
    p.add_argument("--replica", help="the replica the run played (its mav0/scene/mesh.ply and ground truth; default: "
                   "the bundled default replica)")
    p.add_argument("--samples", type=int, default=300_000, help="points drawn in the map's box (default 300000)")
    p.add_argument("--max-cells", type=int, default=6000, help="grid cells checked per figure (default 6000)")
    p.add_argument("--json", action="store_true", help="print the figures as JSON")


def evaluate_run(run: Path, replica: Path, samples: int = 300_000, max_cells: int = 6000) -> dict:
    """The figures of a run folder against its replica (module docstring)."""
    import numpy as np

    from services.app.metrics.occupancy import SceneTruth, grid_figures, voxel_figures
    from services.app.synth.scene import read_ply
    from services.mapping.combined import CombinedMap
    from services.mapping.config import MappingConfig
    from services.mapping.grid import GridBuilder
    from services.mapping.grid_files import read_grid
    from services.mapping.io import load_map
    from shared.config import from_dict
    from shared.map_folder import dense_path
    from shared.metrics.ate import run_alignment

    cfg = MappingConfig()
    if (run / "config.yaml").is_file():
        import yaml

        cfg = from_dict(MappingConfig, (yaml.safe_load((run / "config.yaml").read_text()) or {}).get("mapping", {}))
    mapper = load_map(dense_path(run))
    cm = CombinedMap.of(mapper, cfg.query)
    gt = replica / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    placed = "final" if (run / "trajectory_final.txt").is_file() else "causal"
    T_gt_W = run_alignment(run / f"trajectory_{placed}.txt", gt)
    v, f = read_ply(replica / "mav0" / "scene" / "mesh.ply")
    truth = SceneTruth(v, f, mapper.sensor.voxel_size_m)
    combined, per = voxel_figures(cm, truth, T_gt_W, samples)
    grid_yaml = run / "occupancy_grid.yaml"
    grid = read_grid(grid_yaml) if grid_yaml.is_file() else GridBuilder(cfg.grid, cfg.query).build(mapper)
    cells = grid_figures(grid, cm, truth, T_gt_W, max_cells) if grid is not None else None
    return {"run": str(run), "replica": str(replica), "map_placed_by": placed, "voxel_size_m": cm.voxel_size_m,
            "free_below": cm.cfg.free_below, "samples": samples, "voxels": combined.as_dict(),
            "submaps": {str(k): s.as_dict() for k, s in per.items()},
            "grid": None if cells is None else cells.as_dict() | {
                "resolution_m": grid.resolution_m, "height_band_m": np.asarray(grid.z_band_m).tolist(),
                "cells": int(grid.cells.size), "free_cells": int((grid.cells == 0).sum())}}


def summary_lines(rep: dict) -> list[str]:
    """The figures as the demo prints them."""
    v, g = rep["voxels"], rep["grid"]
    sub = rep["submaps"]
    worst = max(sub.values(), key=lambda s: s["false_free"]) if sub else None
    lines = [f"occupancy false free (voxels)       {100 * v['false_free']:.2f} % of {v['free']} free samples "
             f"(target <= 0.5 %); per submap worst {100 * worst['false_free']:.2f} % of {len(sub)}" if worst else "",
             f"occupancy free recall (voxels)      {100 * v['free_recall']:.1f} % of observed free space (target >= 80 %)"]
    if g is not None:
        lines += [f"grid false free (cells)             {100 * g['false_free']:.2f} % of free cells checked "
                  f"({g['free_cells']} free of {g['cells']}, {g['resolution_m']} m, band "
                  f"{g['height_band_m'][0]:.2f}..{g['height_band_m'][1]:.2f} m)",
                  f"grid free recall (cells)            {100 * g['free_recall']:.1f} % of observed free cells"
                  + (f"; {100 * g['free_recall_whole_band']:.1f} % of those whose whole band was observed"
                     if g.get("free_recall_whole_band") is not None else "")]
    return [ln for ln in lines if ln]


def main(args: argparse.Namespace) -> int:
    from services.app.synth.api import ensure_default_replica
    from services.mapping.io import MapFileError

    run = Path(args.run_dir)
    replica = Path(args.replica) if args.replica else ensure_default_replica(progress=True)
    try:
        rep = evaluate_run(run, replica, args.samples, args.max_cells)
    except (FileNotFoundError, MapFileError, ValueError) as exc:
        print(f"sigmaslam eval occupancy: {exc}", file=sys.stderr)
        return 2
    (run / "occupancy_eval.json").write_text(json.dumps(rep, indent=1))
    if args.json:
        print(json.dumps(rep, indent=1))
    else:
        for line in summary_lines(rep):
            print(line, flush=True)
        for k, s in rep["submaps"].items():
            print(f"  submap {k}: false free {100 * s['false_free']:.2f} % of {s['free']}, free recall "
                  f"{100 * s['free_recall']:.1f} %", flush=True)
    return 0
