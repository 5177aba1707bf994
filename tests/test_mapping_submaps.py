"""Submaps: switching at eps_vol, anchoring in the body frame, poses following keyframes (the mesh
moves), save/load round trip, PLY output, pose look-up by stamp."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from services.mapping.config import SensorModelConfig, SubmapConfig
from services.mapping.io import MapFileError, load_map, save_map, write_ply
from services.mapping.poses import PoseBuffer
from shared.occupancy.query import interpolate
from services.mapping.submaps import SubmapMapper
from shared.geometry import inv_T, make_T, so3_exp
from raycast_depth import DepthRenderer, intrinsics, look_at

W, H = 256, 192  # smaller images keep these tests fast; the geometry does not depend on it
K = intrinsics(W, H)
T_SC = make_T(so3_exp(np.array([0.02, -0.01, 0.03])), np.array([0.05, -0.02, 0.01]))


def corridor() -> o3d.geometry.TriangleMesh:
    m = o3d.geometry.TriangleMesh.create_box(30.0, 3.0, 3.0)
    m.triangles = o3d.utility.Vector3iVector(np.asarray(m.triangles)[:, ::-1])
    return m


def sideways_frames(n: int, step: float):
    """Camera moving along +x, looking at the y = 3 wall from y = 0.5 (new space keeps coming in)."""
    r = DepthRenderer(corridor())
    for i in range(n):
        eye = np.array([1.0 + i * step, 0.5, 1.5])
        T_WC = look_at(eye, eye + np.array([0.0, 1.0, 0.0]))
        yield i * 100_000_000, r.render(K, W, H, T_WC), T_WC


def run(mapper: SubmapMapper, n: int = 30, step: float = 0.15):
    reports = []
    for stamp, d, T_WC in sideways_frames(n, step):
        reports.append((mapper.integrate(d, np.full_like(d, 0.03), K, T_WC, T_SC, stamp), T_WC, stamp))
    return reports


@pytest.fixture(scope="module")
def mapped():
    mapper = SubmapMapper(SensorModelConfig(), SubmapConfig(eps_vol=0.2, min_frames=2))
    return mapper, run(mapper)


def test_new_submap_when_overlap_falls_below_eps_vol(mapped):
    mapper, reports = mapped
    assert 2 <= len(mapper.submaps) <= 10
    for rep, T_WC, stamp in reports:
        if rep.new_submap and rep.submap_id > 0:
            assert rep.overlap < 0.2
            sm = mapper.submaps[rep.submap_id]
            # anchored in the body frame at creation: T_WM = T_WC T_SC^-1
            assert np.allclose(sm.T_WM, T_WC @ inv_T(T_SC)) and sm.anchor_stamp_ns == stamp
        elif not np.isnan(rep.overlap):
            assert rep.overlap >= 0.2
    # never a switch with eps_vol = 0
    one = SubmapMapper(SensorModelConfig(), SubmapConfig(eps_vol=0.0))
    run(one, n=12, step=0.3)
    assert len(one.submaps) == 1


def test_overlap_estimate_tracks_shared_volume():
    mapper = SubmapMapper(SensorModelConfig(), SubmapConfig(overlap_samples=4000))
    frames = list(sideways_frames(12, 0.25))
    _, d0, T0 = frames[0]
    mapper.integrate(d0, np.full_like(d0, 0.03), K, T0, np.eye(4), 0)
    ov = [mapper.overlap(mapper.current, mapper_prep(mapper, d), K, T) for _, d, T in frames]
    assert ov[0] > 0.9 and ov[-1] < 0.15
    assert all(a >= b - 0.05 for a, b in zip(ov, ov[1:]))  # shrinks as the camera moves away


def mapper_prep(mapper, d):
    from services.mapping.sensor_model import prepare_depth

    return prepare_depth(d, np.full_like(d, 0.03), mapper.sensor)[0]


def test_submap_poses_follow_keyframes_and_move_the_mesh(mapped):
    mapper, reports = mapped
    mapper.remesh()
    v0, f0 = mapper.world_mesh()
    assert len(f0) > 1000
    stamps = np.array([st for _, _, st in reports])
    T_WS = np.array([T @ inv_T(T_SC) for _, T, _ in reports])
    ids = np.arange(len(stamps)) + 100
    assert mapper.update_keyframes(ids, stamps, T_WS) == []  # binding only: nothing moves
    assert all(sm.keyframe_id >= 100 for sm in mapper.submaps)
    delta = make_T(so3_exp(np.array([0.0, 0.0, 0.1])), np.array([0.3, -0.2, 0.05]))  # a loop-closure-like correction
    moved = mapper.update_keyframes(ids, stamps, delta @ T_WS)
    assert sorted(moved) == [sm.id for sm in mapper.submaps]
    v1, f1 = mapper.world_mesh()
    assert np.array_equal(f0, f1)
    assert np.allclose(v1, v0 @ delta[:3, :3].T + delta[:3, 3], atol=1e-4)
    mapper.update_keyframes(ids, stamps, T_WS)  # back, for the other tests of this module


def test_submaps_follow_a_final_trajectory_at_their_keyframes(mapped):
    # the non-causal trajectory (one pose per published frame) moves each bound submap as its keyframe moved;
    # a submap whose keyframe the trajectory lacks stays put
    mapper, reports = mapped
    stamps = np.array([st for _, _, st in reports])
    T_WS = np.array([T @ inv_T(T_SC) for _, T, _ in reports])
    ids = np.arange(len(stamps)) + 100
    mapper.update_keyframes(ids, stamps, T_WS)
    assert len(mapper.submaps) >= 3 and all(sm.keyframe_stamp_ns in set(stamps.tolist()) for sm in mapper.submaps)
    before = {sm.id: sm.T_WM.copy() for sm in mapper.submaps}
    delta = make_T(so3_exp(np.array([0.0, 0.0, 0.05])), np.array([0.1, 0.2, 0.0]))
    split = int(np.flatnonzero(stamps == mapper.submaps[1].keyframe_stamp_ns)[0])
    final = T_WS.copy()
    final[split:] = delta @ final[split:]  # the run from the second submap on moved
    last = mapper.submaps[-1]
    keep = stamps != last.keyframe_stamp_ns  # the trajectory lacks the last submap's keyframe
    moved = mapper.follow_trajectory(stamps[keep], final[keep])
    for sm in mapper.submaps:
        late = sm.keyframe_stamp_ns >= stamps[split]
        if sm is last or not late:
            assert sm.id not in moved and np.allclose(sm.T_WM, before[sm.id], atol=1e-9)
        else:
            assert sm.id in moved and np.allclose(sm.T_WM, delta @ before[sm.id], atol=1e-9)
    assert mapper.submaps[1].id in moved
    mapper.follow_trajectory(stamps, T_WS)  # back, for the other tests of this module
    assert all(np.allclose(sm.T_WM, before[sm.id], atol=1e-9) for sm in mapper.submaps)


def test_save_load_round_trip(mapped, tmp_path):
    mapper, _ = mapped
    path = save_map(mapper, tmp_path / "map.npz")
    assert path.is_file() and not list(tmp_path.glob(".*tmp"))
    back = load_map(path)
    assert len(back.submaps) == len(mapper.submaps) and back.sensor == mapper.sensor
    rng = np.random.default_rng(0)
    for a, b in zip(mapper.submaps, back.submaps):
        assert np.allclose(a.T_WM, b.T_WM) and a.keyframe_id == b.keyframe_id and a.n_frames == b.n_frames
        assert a.keyframe_stamp_ns == b.keyframe_stamp_ns
        p = rng.uniform([-1, -1, 0], [4, 3, 5], (3000, 3))
        La, ga, va = interpolate(a.field(), p)
        Lb, gb, vb = interpolate(b.field(), p)
        assert np.array_equal(va, vb) and va.sum() > 100
        assert np.allclose(La[va], Lb[va]) and np.allclose(ga[va], gb[va])
    mapper.remesh()
    back.remesh()
    (va, fa), (vb, fb) = mapper.world_mesh(), back.world_mesh()
    assert len(fa) == len(fb)
    assert np.allclose(np.sort(va, axis=0), np.sort(vb, axis=0), atol=1e-5)
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a map")
    with pytest.raises(MapFileError):
        load_map(bad)


def test_ply_written_readable(mapped, tmp_path):
    mapper, _ = mapped
    mapper.remesh()
    v, f = mapper.world_mesh()
    path = write_ply(tmp_path / "mesh.ply", v, f, np.full((len(v), 3), 200, np.uint8))
    m = o3d.io.read_triangle_mesh(str(path))
    assert len(m.vertices) == len(v) and len(m.triangles) == len(f)
    assert np.allclose(np.asarray(m.vertices), v, atol=1e-6) and np.array_equal(np.asarray(m.triangles), f)


def test_pose_buffer_exact_and_interpolated():
    buf = PoseBuffer(capacity=5)
    Ts = [make_T(so3_exp(np.array([0.0, 0.0, 0.2 * i])), np.array([i, 0.0, 0.0])) for i in range(7)]
    for i, T in enumerate(Ts):
        buf.add(i * 1_000_000_000, T)
    assert len(buf) == 5  # bounded: the two oldest went
    assert np.allclose(buf.lookup(3_000_000_100, 1000, 2_000_000_000), Ts[3])
    mid = buf.lookup(3_500_000_000, 1000, 2_000_000_000)
    assert np.allclose(mid, make_T(so3_exp(np.array([0, 0, 0.7])), np.array([3.5, 0, 0])))
    assert buf.lookup(3_500_000_000, 1000, 500_000_000) is None  # gap too large
    assert buf.lookup(1_000_000_000, 1000, 2_000_000_000) is None  # dropped from the buffer
    assert buf.lookup(9_000_000_000, 1000, 2_000_000_000) is None  # not arrived yet
    with pytest.raises(ValueError):
        buf.add(10, np.full((4, 4), np.nan))


def test_bad_frames_raise_clear_errors():
    mapper = SubmapMapper()
    d = np.full((H, W), 2.0, np.float32)
    s = np.full((H, W), 0.03, np.float32)
    with pytest.raises(ValueError, match="intrinsics"):
        mapper.integrate(d, s, np.zeros((3, 3)), np.eye(4), np.eye(4), 0)
    with pytest.raises(ValueError, match="T_WC"):
        mapper.integrate(d, s, K, np.full((4, 4), np.nan), np.eye(4), 0)
    with pytest.raises(ValueError, match="shape"):
        mapper.integrate(d, s[:, :10], K, np.eye(4), np.eye(4), 0)
    assert mapper.submaps == []  # nothing was created by the rejected frames


def test_field_message_round_trip_answers_the_same_queries(mapped):
    from services.mapping.export import field_message
    from shared.occupancy.message import field_of_message
    from shared.codec import decode, encode
    from shared.messages import OccupancyField

    mapper, _ = mapped
    sm = mapper.submaps[0]
    msg = decode(encode(field_message(sm, mapper.sensor.l_min)), OccupancyField)
    assert msg.submap_id == 0 and np.allclose(msg.T_WM, sm.T_WM) and msg.log_odds.shape[1:] == (8, 8, 8)
    assert len(msg.block_ijk) == len(sm.store.refined_slots())
    field = field_of_message(msg)
    mapper.remesh()
    v, _ = sm.mesher.mesh()  # surface points: where the back end evaluates L and grad L
    L0, g0, v0 = interpolate(sm.field(), v)
    L1, g1, v1 = interpolate(field, v)
    assert v0.mean() > 0.9 and np.array_equal(v0, v1)
    assert np.allclose(L0[v0], L1[v1]) and np.allclose(g0[v0], g1[v1])
    assert np.mean(np.abs(L1[v1]) < 1e-3) > 0.999  # the mesh is the L = 0 surface (but for rare interior vertices)


def test_mesh_leaves_out_surfaces_the_map_is_unsure_of():
    """Half of each image is sure (sigma 3 cm), half unsure (30 cm): the published mesh keeps the sure half's wall,
    with sigma_map near its 3 cm (eq. 7), and leaves the unsure half out; 0 keeps both."""
    def mapped(limit):
        mapper = SubmapMapper(SensorModelConfig(), SubmapConfig(eps_vol=0.0, mesh_max_sigma_m=limit))
        for stamp, d, T_WC in sideways_frames(4, 0.05):
            s = np.full_like(d, 0.03)
            s[:, W // 2:] = 0.3
            mapper.integrate(d, s, K, T_WC, T_SC, stamp)
        mapper.remesh()
        return mapper

    sure, every = mapped(0.055), mapped(0.0)
    v_all, f_all, sig_all = every.mesh(every.submaps[0])
    v, f, sig = sure.mesh(sure.submaps[0])
    assert len(f_all) > 1000 and 0 < len(f) < 0.8 * len(f_all)
    assert f.max() < len(v) and len(sig) == len(v) and np.all(sig <= 0.055)
    v_W = v @ sure.submaps[0].T_WM[:3, :3].T + sure.submaps[0].T_WM[:3, 3]
    on_corridor = ((np.abs(v_W[:, 1] - 3.0) < 0.1) | (np.abs(v_W[:, 0]) < 0.1) | (np.abs(v_W[:, 2]) < 0.1)
                   | (np.abs(v_W[:, 2] - 3.0) < 0.1))  # the far wall, the end wall, floor and ceiling
    assert on_corridor.mean() > 0.95 and abs(np.median(sig) - 0.03) < 0.01
    # the unsure half: wall vertices of the unfiltered mesh that the sure mesh has none near
    vall_W = v_all @ every.submaps[0].T_WM[:3, :3].T + every.submaps[0].T_WM[:3, 3]
    unsure = vall_W[sig_all > 0.1]
    assert len(unsure) > 100 and np.median(np.abs(unsure[:, 1] - 3.0)) < 0.2
    from scipy.spatial import cKDTree

    assert np.median(cKDTree(v_W).query(unsure)[0]) > 0.1
    assert len(sure.world_mesh()[1]) == len(f)
