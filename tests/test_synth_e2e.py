"""End-to-end check of a generated replica: every depth image lies on the replica's own mesh, and the IMU is
aligned with its ground truth. Reduced form: a 1 s replica (or the first 20 frames of the cached default
replica); ``SIGMASLAM_E2E=full``: the bundled default replica (generated if absent, ~500 stereo frames)."""
from __future__ import annotations

import os

import numpy as np
import open3d as o3d
import pytest

from shared.camera import load_rig
from services.app.synth.depth_io import DepthFolder
from shared.euroc import read_euroc_csv
from services.app.synth.imu_sim import read_imu_csv, time_offset
from services.app.synth.trajectory import Trajectory
from services.app.synth.api import DEFAULT, replica_name
from services.app.synth.replica import ReplicaSpec
from services.app.synth.scene import read_ply

FULL = os.environ.get("SIGMASLAM_E2E", "") == "full"


@pytest.mark.e2e
def test_replica_depth_on_mesh_and_imu_alignment(tmp_path):
    from shared.paths import data_dir
    from services.app.synth.api import ensure_default_replica, ensure_replica

    cached = data_dir() / "replicas" / replica_name(ReplicaSpec(**DEFAULT))
    if FULL:
        path, n_frames = ensure_default_replica(progress=False), None
    elif (cached / "replica.yaml").is_file():
        path, n_frames = cached, 20
    else:
        path, n_frames = ensure_replica("V1_02", "vicon-a", "real", duration_s=1.0, start_s=30.0, root=tmp_path,
                                        progress=False), None
    mav0 = path / "mav0"
    v, f = read_ply(mav0 / "scene" / "mesh.ply")
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
    cam = load_rig(path)[0]
    gt = Trajectory(read_euroc_csv(mav0 / "state_groundtruth_estimate0" / "data.csv"), knot_spacing_s=0.02)
    depth = DepthFolder(mav0 / "depth0")
    uv = cam.camera.pixel_grid()[::97]
    rays = cam.camera.unproject(uv)
    worst = 0.0
    for t in depth.stamps_ns[:n_frames]:
        z = depth.read(t).ravel()[::97]
        ok = np.isfinite(z)
        T_WC = gt.pose(int(t)) @ cam.T_SC
        p_W = (rays[ok] * z[ok, None]) @ T_WC[:3, :3].T + T_WC[:3, 3]
        worst = max(worst, float(rc.compute_distance(o3d.core.Tensor(p_W.astype(np.float32))).numpy().max()))
    print(f"{path.name}: {len(depth.stamps_ns[:n_frames])} frames, GT depth -> mesh max {worst * 1e3:.3f} mm")
    # the GT file is the replica's trajectory sampled at 200 Hz; refitting it adds a little interpolation error
    assert worst < 2e-3
    imu = read_imu_csv(mav0 / "imu0" / "data.csv")
    if imu.stamps_ns[-1] - imu.stamps_ns[0] > 3 * 10**9:
        d, _, corr = time_offset(gt, imu, max_offset_ns=20_000_000)
        print(f"gyro vs GT body rate: best lag {d / 1e6:.1f} ms, correlation {corr.max():.3f}")
        assert abs(d) <= 1_000_000
