"""The mapping loop's map-to-map points (mapping.o2p_points): pooled per submap, published once when the
submap closes, in its frame M, on the mapped surfaces; off by default."""

from __future__ import annotations

import numpy as np
import open3d as o3d

from services.mapping.config import MappingConfig, SubmapConfig
from services.mapping.node import make_node
from shared import topics
from shared import messages as m
from shared.codec import Header
from raycast_depth import DepthRenderer, intrinsics, look_at, room_scene

W, H = 160, 120
K = intrinsics(W, H)


def frames(n=6):
    for i, a in enumerate(np.linspace(0, 2 * np.pi, n, endpoint=False)):
        eye = np.array([3.0 + 0.8 * np.cos(a), 2.5 + 0.8 * np.sin(a), 1.5])
        yield (i + 1) * 100_000_000, look_at(eye, eye + np.array([np.cos(a), np.sin(a), -0.2]))


def run(cfg: MappingConfig):
    loop = make_node(cfg)
    renderer = DepthRenderer(room_scene())
    published = []
    for stamp, T_WC in frames():
        loop.on_state(m.EstimatorState(header=Header(stamp_ns=stamp, frame_id="W"), T_WS=T_WC, v_W=np.zeros(3),
                                       gyro_bias=np.zeros(3), acc_bias=np.zeros(3), covariance=np.eye(15)))
        d = renderer.render(K, W, H, T_WC)
        out = loop.on_depth(m.DepthFrame(header=Header(stamp_ns=stamp, frame_id="cam0"), depth=d,
                                         sigma=np.full_like(d, 0.02), K=K, T_WC=np.eye(4), source="fused"))
        published += [e.msg for e in out if e.topic is topics.MAP_O2P_POINTS]
    return loop, published


def test_points_of_closed_submaps_lie_on_the_surfaces():
    # every frame after the first turns away from the previous: each closes a submap (min_frames 1)
    cfg = MappingConfig(o2p_points=300, submaps=SubmapConfig(eps_vol=0.99, min_frames=1))
    loop, pub = run(cfg)
    closed = len(loop.mapper.submaps) - 1
    assert closed >= 2 and [p.submap_id for p in pub] == list(range(closed))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(room_scene()))
    for p in pub:
        assert 100 <= len(p.points_M) <= 300 and p.header.frame_id == f"M{p.submap_id}"
        T_WM = loop.mapper.submaps[p.submap_id].T_WM
        p_W = p.points_M.astype(float) @ T_WM[:3, :3].T + T_WM[:3, 3]
        assert np.percentile(scene.compute_distance(o3d.core.Tensor(p_W.astype(np.float32))).numpy(), 99) < 5e-3


def test_off_by_default():
    loop, pub = run(MappingConfig(submaps=SubmapConfig(eps_vol=0.99, min_frames=1)))
    assert pub == [] and loop.points is None and len(loop.mapper.submaps) >= 3
