"""The 3D export (services/mapping/voxel_export.py) of a small known map, read back with numpy and open3d, and
``sigmaslam map grid`` / ``map export`` on a saved map."""

from __future__ import annotations

import argparse

import numpy as np
import open3d as o3d

from services.mapping.combined import CombinedMap
from services.mapping.io import save_map
from services.mapping.submaps import SubmapMapper
from shared.geometry import make_T


def _wall_map() -> SubmapMapper:
    """A wall 2 m in front of a camera (z forward) that moves sideways: free space in front, the wall at z = 2."""
    w, h, sigma = 64, 48, 0.02
    K = np.array([[40.0, 0, w / 2 - 0.5], [0, 40.0, h / 2 - 0.5], [0, 0, 1]])
    mapper = SubmapMapper()
    for i in range(6):
        depth = np.full((h, w), 2.0, np.float32)
        mapper.integrate(depth, np.full_like(depth, sigma), K, make_T(np.eye(3), [0.1 * i, 0, 0]), np.eye(4),
                         i * 50_000_000)
    return mapper


def test_voxels_npz_and_ply(tmp_path):
    from services.mapping.voxel_export import NPZ_FILE, PLY_FILE, write_voxels

    cm = CombinedMap.of(_wall_map())
    npz, ply, n = write_voxels(cm, tmp_path)
    assert npz.name == NPZ_FILE and ply.name == PLY_FILE
    with np.load(npz) as z:
        a = {k: z[k] for k in z.files}
    assert str(a["frame"]) == "W" and a["voxel_size_m"] == 0.025 and a["free_below"] == cm.cfg.free_below
    occ = (a["occupied_ijk"] + 0.5) * a["voxel_size_m"]
    free = (a["free_ijk"] + 0.5) * a["voxel_size_m"]
    assert len(occ) == n["occupied"] > 1000 and len(free) == n["free"] > 3 * len(occ)
    assert np.all(np.abs(occ[:, 2] - 2.0) < 0.1)  # the wall's surface band
    assert free[:, 2].max() < 2.0 - 0.03 and (a["free_log_odds"] < cm.cfg.free_below).all()
    assert (a["occupied_log_odds"] > 0).all()
    np.testing.assert_array_equal(cm.points(occ).state, 2)  # the combined map agrees at the exported centres
    cloud = o3d.io.read_point_cloud(str(ply))
    assert len(cloud.points) == len(occ)
    np.testing.assert_allclose(np.asarray(cloud.points), occ, atol=1e-5)


def test_map_grid_and_export_commands(tmp_path, capsys):
    from services.app.map_occupancy_cmd import main
    from services.mapping.grid_files import read_grid

    run = tmp_path / "run"
    save_map(_wall_map(), run / "map" / "dense.npz")
    ns = dict(out=None, resolution=0.05, band=None, floor_z=1.0, set=[])
    # the wall is vertical here (z forward): with the floor at 1 m and a band above it, the grid sees nothing
    # occupied below the wall's top edge... it is a plane along x-y at z = 2, so the band z 1.1..2.5 holds it
    assert main(argparse.Namespace(map_command="grid", dir=str(run), **ns)) == 0
    g = read_grid(run / "occupancy_grid.yaml")
    assert g.resolution_m == 0.05 and np.allclose(g.z_band_m, [1.1, 2.5]) and (g.cells == 100).any()
    assert main(argparse.Namespace(map_command="export", dir=str(run / "map"), out=str(tmp_path / "x"),
                                   set=[])) == 0
    assert (tmp_path / "x" / "occupancy_voxels.npz").is_file() and (tmp_path / "x" / "occupied_voxels.ply").is_file()
    out = capsys.readouterr().out
    assert "occupancy_grid.pgm" in out and "occupied" in out
    assert main(argparse.Namespace(map_command="grid", dir=str(tmp_path / "nothing"), **ns)) == 2
