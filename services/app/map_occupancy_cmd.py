"""``sigmaslam map grid DIR`` and ``sigmaslam map export DIR``: the occupancy outputs a run writes, made again from a
saved map (``DIR/map/dense.npz``), with other settings if wanted (docs/occupancy.md).

- ``grid`` writes ``OUT/occupancy_grid.pgm`` + ``.yaml`` (ROS map_server; OUT defaults to DIR): the combined map's
  2D grid over a height band (services/mapping/grid.py);
- ``export`` writes ``OUT/occupancy_voxels.npz`` and ``OUT/occupied_voxels.ply`` (services/mapping/voxel_export.py).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path


def add_parsers(sub) -> None:
    q = sub.add_parser("grid", help="write the 2D occupancy grid (ROS map_server PGM + YAML) of a saved map",
                       description="write the 2D occupancy grid (ROS map_server PGM + YAML) of a saved map")
    q.add_argument("dir", help="a run's output folder, or its map/ folder")
    q.add_argument("--out", help="folder to write occupancy_grid.pgm/.yaml into (default: the run folder)")
    q.add_argument("--resolution", type=float, help="cell edge [m] (default mapping.grid.resolution_m)")
    q.add_argument("--band", type=float, nargs=2, metavar=("MIN", "MAX"),
                   help="height band above the floor [m] (default mapping.grid.band_min_m, band_max_m)")
    q.add_argument("--floor-z", type=float, help="the floor's height in W [m] (default: found in the map)")
    q.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a mapping.* field")
    q = sub.add_parser("export", help="write the combined map's voxels (occupancy_voxels.npz, occupied_voxels.ply)",
                       description="write the combined map's voxels (occupancy_voxels.npz, occupied_voxels.ply)")
    q.add_argument("dir", help="a run's output folder, or its map/ folder")
    q.add_argument("--out", help="folder to write into (default: the run folder)")
    q.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a mapping.* field")


def _run_folder(d: str) -> Path:
    p = Path(d)
    return p.parent if p.name == "map" else p


def main(args: argparse.Namespace) -> int:
    from services.app.system_config import load_system_config
    from services.mapping.io import MapFileError, load_map
    from shared.map_folder import dense_path

    cfg = load_system_config(None, args.set).mapping
    path = dense_path(args.dir)
    try:
        mapper = load_map(path)
    except (FileNotFoundError, MapFileError) as exc:
        print(f"sigmaslam map {args.map_command}: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out) if args.out else _run_folder(args.dir)
    if args.map_command == "export":
        from services.mapping.combined import CombinedMap
        from services.mapping.voxel_export import write_voxels

        npz, ply, n = write_voxels(CombinedMap.of(mapper, cfg.query), out)
        print(f"wrote {npz} ({n['occupied']} occupied, {n['free']} free voxels) and {ply}", flush=True)
        return 0
    from services.mapping.grid import GridBuilder
    from services.mapping.grid_files import write_grid

    g = cfg.grid
    if args.resolution is not None:
        g = dataclasses.replace(g, resolution_m=args.resolution)
    if args.band is not None:
        g = dataclasses.replace(g, band_min_m=args.band[0], band_max_m=args.band[1])
    if args.floor_z is not None:
        g = dataclasses.replace(g, floor="fixed", floor_z_m=args.floor_z)
    try:
        grid = GridBuilder(g, cfg.query).build(mapper)
    except ValueError as exc:
        print(f"sigmaslam map grid: {exc}", file=sys.stderr)
        return 2
    if grid is None:
        print(f"sigmaslam map grid: {path} holds no occupied voxel to find the floor from (give --floor-z)",
              file=sys.stderr)
        return 1
    pgm, ym = write_grid(grid, out)
    h, w = grid.cells.shape
    shares = [(grid.cells == v).mean() for v in (0, 100, 255)]
    print(f"wrote {pgm} and {ym}: {w} x {h} cells of {grid.resolution_m} m, band z {grid.z_band_m[0]:.2f} .. "
          f"{grid.z_band_m[1]:.2f} m in W (floor {grid.floor_z_m:.2f} m); {shares[0]:.1%} free, {shares[1]:.1%} "
          f"occupied, {shares[2]:.1%} unknown", flush=True)
    return 0
