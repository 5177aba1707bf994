"""A 2D grid (services/mapping/grid.py) on disk in the ROS map_server format: ``NAME.pgm`` (8-bit binary PGM, the
top image row is the highest y) and ``NAME.yaml``:

- ``image``: the PGM's file name, beside the YAML;
- ``resolution``: cell edge [m]; ``origin``: [x, y, yaw] in W of the lower-left pixel's corner (yaw 0);
- ``negate: 0``, ``occupied_thresh: 0.65``, ``free_thresh: 0.196``, ``mode: trinary``: a reader takes
  p = (255 - value) / 255, occupied when p > occupied_thresh, free when p < free_thresh, else unknown; the pixels are
  free 254, occupied 0, unknown 205;
- extra keys a map_server ignores: ``frame: W`` (the gravity-aligned world frame of the run), ``height_band:
  [z_min, z_max]`` (the band of W the grid summarises [m]) and ``floor_z`` [m].
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from services.mapping.grid import FREE_CELL, OCCUPIED_CELL, UNKNOWN_CELL, Grid2D
from shared.map_folder import atomic_write

FREE_PX, OCCUPIED_PX, UNKNOWN_PX = 254, 0, 205
OCCUPIED_THRESH, FREE_THRESH = 0.65, 0.196


def write_grid(grid: Grid2D, folder: str | Path, name: str = "occupancy_grid") -> tuple[Path, Path]:
    """Write ``folder/NAME.pgm`` and ``folder/NAME.yaml`` (atomically); returns their paths."""
    folder = Path(folder)
    px = np.full(grid.cells.shape, UNKNOWN_PX, np.uint8)
    px[grid.cells == FREE_CELL] = FREE_PX
    px[grid.cells == OCCUPIED_CELL] = OCCUPIED_PX
    px = px[::-1]  # image rows top-down: the first is the highest y
    h, w = px.shape
    pgm = atomic_write(folder / f"{name}.pgm",
                       lambda fh: (fh.write(f"P5\n{w} {h}\n255\n".encode("ascii")), fh.write(px.tobytes())))
    meta = {"image": pgm.name, "resolution": float(grid.resolution_m),
            "origin": [float(grid.origin_xy_m[0]), float(grid.origin_xy_m[1]), 0.0], "negate": 0,
            "occupied_thresh": OCCUPIED_THRESH, "free_thresh": FREE_THRESH, "mode": "trinary", "frame": "W",
            "height_band": [float(grid.z_band_m[0]), float(grid.z_band_m[1])], "floor_z": float(grid.floor_z_m)}
    text = "# 2D occupancy grid of a sigmaslam map (ROS map_server format; frame, height_band, floor_z: extra keys)\n"
    ym = atomic_write(folder / f"{name}.yaml", lambda fh: fh.write((text + yaml.safe_dump(meta, sort_keys=False))
                                                                   .encode()))
    return pgm, ym


def read_grid(yaml_path: str | Path) -> Grid2D:
    """A grid written by :func:`write_grid` (or any trinary map_server map with negate 0) as a :class:`Grid2D`."""
    import cv2

    yaml_path = Path(yaml_path)
    meta = yaml.safe_load(yaml_path.read_text())
    img = cv2.imread(str(yaml_path.parent / meta["image"]), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 2:
        raise ValueError(f"{yaml_path}: image {meta['image']} is not a grayscale image")
    p = (255.0 - img[::-1].astype(float)) / 255.0
    cells = np.full(img.shape, UNKNOWN_CELL, np.uint8)
    cells[p < float(meta["free_thresh"])] = FREE_CELL
    cells[p > float(meta["occupied_thresh"])] = OCCUPIED_CELL
    band = meta.get("height_band", [np.nan, np.nan])
    return Grid2D(cells, float(meta["resolution"]), np.array(meta["origin"][:2], float), np.array(band, float),
                  float(meta.get("floor_z", np.nan)))
