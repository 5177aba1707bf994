"""04: load the map a run saved, look inside it, and export a mesh.

The mapping service keeps the map as occupancy submaps (paper eq. 2-4, sec. IV-E): submap j is a sparse field of
log-odds L (L > 0 occupied, L < 0 free, surface at L = 0) and observation counts w on 2.5 cm voxels, stored in its
own frame M_j (the body frame at the submap's creation) with a pose ``T_WM`` that follows the estimator's keyframes
and, at the end, the non-causal trajectory. With an output folder (``sigmaslam run ... --out DIR``,
``sigmaslam demo``, ``sigmaslam mapping --out DIR``) it writes ``DIR/map/dense.npz`` (the whole map, reloadable),
``DIR/mesh.ply`` (all submaps in W) and ``DIR/submaps/submap_NNN.ply`` (each in its own frame).

This script reloads ``map/dense.npz`` with :func:`services.mapping.io.load_map` (the loader the mapping service uses to
resume after a restart), prints each submap, queries the field (what the occupancy-to-point factors of the back end
do, eq. 6-7), and writes the world mesh again::

    sigmaslam demo                                         # or: sigmaslam run DATASET CONFIG --out out/run
    python -m examples.04_load_saved_map out/demo          # writes out/demo/mesh_from_map.ply
    python -m examples.04_load_saved_map out/demo/map/dense.npz --out /tmp/map.ply
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from services.mapping.io import load_map, write_ply
from shared.occupancy.query import FREE, OCCUPIED, interpolate, state


def describe_submap(mapper, sm) -> dict:
    """Facts of one submap, and what its field says at and around its surface."""
    sensor = mapper.sensor
    v_M, faces, _ = mapper.mesh(sm)  # the mesh as published (faces the map is unsure of left out), in M_j [m]
    row = {"id": sm.id, "frames": sm.n_frames, "blocks": sm.store.n_blocks, "vertices": len(v_M), "faces": len(faces),
           "p_WM": sm.T_WM[:3, 3].tolist(), "keyframe_id": sm.keyframe_id}
    nan = float("nan")
    if not len(v_M):
        return {**row, "median_abs_L_at_vertices": nan, "median_sigma_map_m": nan, "free_in_front": nan,
                "occupied_behind": nan}
    # 3. Query the field where the surface is (trilinear L and its gradient, as the occupancy-to-point factors
    #    do). At the mesh vertices L is ~0, and the gradient gives the map's own depth uncertainty of eq. 7:
    #    sigma_map = |l_min| / (3 |grad L|).
    field = sm.field()
    L, grad, valid = interpolate(field, v_M)
    g = np.linalg.norm(grad[valid], axis=1)
    sigma_map = abs(sensor.l_min) / (3 * g)
    # ... and what the map says two voxels in front of and behind the surface along the gradient (L grows into
    #     the occupied side): free in front, occupied behind (within the surface thickness tau).
    n = grad[valid] / g[:, None]
    step = 2 * sensor.voxel_size_m
    front, behind = state(field, v_M[valid] - step * n), state(field, v_M[valid] + step * n)
    return {**row, "median_abs_L_at_vertices": float(np.median(np.abs(L[valid]))),
            "median_sigma_map_m": float(np.median(sigma_map)), "free_in_front": float(np.mean(front == FREE)),
            "occupied_behind": float(np.mean(behind == OCCUPIED))}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("path", help="a run folder holding map/dense.npz, or that file itself")
    ap.add_argument("--out", metavar="PLY", help="mesh to write (default: <run folder>/mesh_from_map.ply)")
    args = ap.parse_args(argv)
    path = Path(args.path)
    map_file = path / "map" / "dense.npz" if path.is_dir() else path
    run_dir = map_file.parent.parent  # the run folder: DIR/map/dense.npz
    out = Path(args.out) if args.out else run_dir / "mesh_from_map.ply"

    # 1. Load. The file holds every submap's voxel blocks, its pose T_WM, its keyframe binding T_KM and the sensor
    #    model it was built with; meshes are not stored but rebuilt from the field.
    mapper = load_map(map_file)
    vs = mapper.sensor.voxel_size_m
    print(f"{map_file}: {len(mapper.submaps)} submaps, {vs * 100:g} cm voxels, l_min {mapper.sensor.l_min}, "
          f"{mapper.nbytes() / 1e6:.1f} MB")
    report = run_dir / "mapping.json"  # written by the mapping service into the run folder (counts, timings)
    if report.is_file():
        counts = json.loads(report.read_text()).get("counts", {})
        print(f"mapping.json counts: {counts}")

    # 2. Mesh every submap (marching cubes at L = 0, services/mapping/mesh.py), then look at each one.
    mapper.remesh(None)
    rows = [describe_submap(mapper, sm) for sm in mapper.submaps]
    for r in rows:
        x, y, z = r["p_WM"]
        print(f"submap {r['id']}: {r['frames']} frames, {r['blocks']} blocks, {r['vertices']} vertices; "
              f"p_WM [{x:.2f} {y:.2f} {z:.2f}] m, keyframe {r['keyframe_id']}; "
              f"|L| at vertices {r['median_abs_L_at_vertices']:.2f}, sigma_map {100 * r['median_sigma_map_m']:.1f} cm; "
              f"{2 * vs * 100:g} cm in front free {r['free_in_front']:.0%}, behind occupied {r['occupied_behind']:.0%}")

    # 4. Export: all submaps in W (each vertex moved by its submap's T_WM), as a binary PLY any mesh tool opens.
    v_W, f_W = mapper.world_mesh()
    write_ply(out, v_W, f_W)
    lo, hi = (v_W.min(axis=0), v_W.max(axis=0)) if len(v_W) else (np.zeros(3), np.zeros(3))
    extent = (hi - lo).astype(float)
    print(f"wrote {out}: {len(v_W)} vertices, {len(f_W)} faces, extent {np.round(extent, 2).tolist()} m")
    return {"map": str(map_file), "submaps": rows, "mesh": str(out), "vertices": int(len(v_W)),
            "faces": int(len(f_W)), "extent_m": extent.tolist(), "voxel_size_m": vs}


if __name__ == "__main__":
    main()
