"""The combined map as voxels of W, for planners that work in 3D: ``occupancy_voxels.npz`` and
``occupied_voxels.ply``, from a run (written with the map) or a saved map (``sigmaslam map export DIR``).

The combined map (services/mapping/combined.py: every submap at its current pose, the largest observed log-odds
where they overlap) is sampled at the centres of a lattice of W with the map's voxel size, over the bounding box of
the submaps' blocks: lattice voxel (i, j, k) has its centre at ``(ijk + 0.5) * voxel_size_m`` in W. Every observed
centre is kept. ``occupancy_voxels.npz`` holds

- ``occupied_ijk`` (N, 3) int32, ``occupied_log_odds`` (N,) float32: centres with L > occupied_above;
- ``free_ijk`` (M, 3) int32, ``free_log_odds`` (M,) float32: centres with L < free_below;
- ``voxel_size_m``, ``occupied_above``, ``free_below`` (float64 scalars) and ``frame`` ('W').

Centres between the two thresholds (uncertain) and unobserved ones are not listed: unknown. ``occupied_voxels.ply``
is the occupied centres in W as a point cloud with a ``log_odds`` value per point (binary PLY).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from services.mapping.combined import FREE, OCCUPIED, CombinedMap
from services.mapping.io import write_ply
from shared.map_folder import atomic_write

NPZ_FILE, PLY_FILE = "occupancy_voxels.npz", "occupied_voxels.ply"


def lattice_bounds(cm: CombinedMap) -> tuple[np.ndarray, np.ndarray] | None:
    """Lowest and highest lattice index (3,) int64 that the submaps' blocks can reach in W (None: empty map)."""
    vs, lo, hi = cm.voxel_size_m, [], []
    for v in cm.views:
        if v.hi_ijk[0] < v.lo_ijk[0]:
            continue
        a, b = v.lo_ijk * vs, (v.hi_ijk + 1) * vs
        box = np.array([[x, y, z] for x in (a[0], b[0]) for y in (a[1], b[1]) for z in (a[2], b[2])])
        box_W = box @ v.T_WM[:3, :3].T + v.T_WM[:3, 3]
        lo.append(np.floor(box_W.min(0) / vs))
        hi.append(np.floor(box_W.max(0) / vs))
    if not lo:
        return None
    return np.min(lo, axis=0).astype(np.int64), np.max(hi, axis=0).astype(np.int64)


def combined_voxels(cm: CombinedMap) -> dict[str, np.ndarray]:
    """The arrays of ``occupancy_voxels.npz`` (module docstring), sampled slab by slab along z."""
    vs = cm.voxel_size_m
    out = {"occupied_ijk": [], "occupied_log_odds": [], "free_ijk": [], "free_log_odds": []}
    bounds = lattice_bounds(cm)
    if bounds is not None:
        lo, hi = bounds
        ii, jj = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1), indexing="ij")
        plane = np.column_stack([ii.ravel(), jj.ravel()])
        for k in range(lo[2], hi[2] + 1):
            ijk = np.column_stack([plane, np.full(len(plane), k)])
            L, _ = cm.log_odds_many((ijk + 0.5) * vs)
            st = cm.classify(L)
            for name, want in (("occupied", OCCUPIED), ("free", FREE)):
                keep = st == want
                out[f"{name}_ijk"].append(ijk[keep].astype(np.int32))
                out[f"{name}_log_odds"].append(L[keep].astype(np.float32))
    arrays = {k: (np.concatenate(v) if v else np.zeros((0, 3) if k.endswith("ijk") else 0,
                                                       np.int32 if k.endswith("ijk") else np.float32))
              for k, v in out.items()}
    arrays.update(voxel_size_m=np.float64(vs), occupied_above=np.float64(cm.cfg.occupied_above),
                  free_below=np.float64(cm.cfg.free_below), frame=np.array("W"))
    return arrays


def write_voxels(cm: CombinedMap, folder: str | Path) -> tuple[Path, Path, dict[str, int]]:
    """Write ``folder/occupancy_voxels.npz`` and ``folder/occupied_voxels.ply``; returns their paths and counts."""
    folder = Path(folder)
    arrays = combined_voxels(cm)
    npz = atomic_write(folder / NPZ_FILE, lambda fh: np.savez_compressed(fh, **arrays))
    p = (arrays["occupied_ijk"] + 0.5) * arrays["voxel_size_m"]
    ply = write_ply(folder / PLY_FILE, p, np.zeros((0, 3), np.int32), scalars={"log_odds": arrays["occupied_log_odds"]})
    return npz, ply, {"occupied": len(arrays["occupied_ijk"]), "free": len(arrays["free_ijk"])}
