"""Frame-to-map and map-to-map factor selection (sec. IV-C): lowest-sigma depth points, o(k) = oldest covisible
submap with >= M_min points in its field, factors that pull window states back onto the map."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import X

from services.backend.o2p.config import O2PConfig
from services.backend.o2p.terms import OccupancyTerms
from shared.occupancy.o2p_points import SubmapPointPool, select_depth_points
from shared.occupancy.blocks import BlockStore
from services.mapping.export import field_message
from services.mapping.mesh import ChunkMesher
from services.mapping.submaps import Submap
from shared.geometry import inv_T, make_T, so3_exp
from tests.o2p_room import H, K, W, view
from raycast_depth import intrinsics, room_scene

S = 1_000_000_000  # 1 s in ns


class Anchors:
    """A fixed SubmapAnchoring (services/backend/window/protocols.py), as the loop-closing back end's PublishedFrame
    answers: ``published`` creation stamp -> (keyframe state, its pose as published), ``C`` = T_W'W or None."""

    def __init__(self, published=None, C=None):
        self.published, self.C = published or {}, C

    def anchor_of(self, stamp_ns, T_WM):
        n, T_WK = self.published[stamp_ns]
        return n, inv_T(T_WK) @ T_WM

    def correction(self):
        return self.C


def perturbed(T, seed, rot_deg=2.0, trans_m=0.04):
    rng = np.random.default_rng(seed)
    a, t = rng.normal(size=3), rng.normal(size=3)
    return T @ make_T(so3_exp(a / np.linalg.norm(a) * np.radians(rot_deg)), t / np.linalg.norm(t) * trans_m)


def solve(factors, values):
    g = gtsam.NonlinearFactorGraph()
    for f in factors:
        g.add(f)
    return gtsam.LevenbergMarquardtOptimizer(g, values).optimize()


def err(T, T_true):
    d = inv_T(T_true) @ T
    return np.degrees(np.linalg.norm(gtsam.Rot3(d[:3, :3]).ypr())), np.linalg.norm(d[:3, 3])


def test_select_depth_points_lowest_sigma_spread_and_back_projected():
    rng = np.random.default_rng(0)
    depth = rng.uniform(1, 4, (H, W)).astype(np.float32)
    sigma = (0.01 * depth**2).astype(np.float32)
    depth[:10] = np.nan  # invalid rows never chosen
    p, s = select_depth_points(depth, sigma, K, 200)
    assert len(p) == 200 and np.all(np.diff(s) >= 0)
    u = p[:, 0] / p[:, 2] * K[0, 0] + K[0, 2]
    v = p[:, 1] / p[:, 2] * K[1, 1] + K[1, 2]
    ui, vi = np.rint(u).astype(int), np.rint(v).astype(int)
    assert np.allclose([u, v], [ui, vi], atol=1e-6) and (vi >= 10).all()
    assert np.allclose(depth[vi, ui], p[:, 2]) and np.allclose(sigma[vi, ui], s)
    # one point per cell: the chosen pixels spread over the valid image, and each beats its cell-mates
    cell = max(1, int(np.sqrt(H * W / 800)))
    assert len(np.unique((vi // cell) * 1000 + ui // cell)) == 200
    assert s.max() < np.percentile(sigma[10:], 50)
    assert select_depth_points(np.full((H, W), np.nan, np.float32), sigma, K, 200)[0].shape == (0, 3)
    with pytest.raises(ValueError):
        select_depth_points(depth, sigma[:5], K, 200)


@pytest.mark.parametrize("shape, cell", [((37, 53), 4), ((40, 48), 8), ((25, 31), 1)])
def test_select_depth_points_takes_each_cells_lowest_sigma_as_a_pixel_loop_does(shape, cell):
    """Against a loop over the cells (partial cells at the edges, invalid pixels, ties in sigma)."""
    rng = np.random.default_rng(cell)
    Hs, Ws = shape
    depth = rng.uniform(1, 4, shape).astype(np.float32)
    sigma = np.round(rng.uniform(0.01, 0.05, shape), 2).astype(np.float32)  # few distinct values: many ties
    depth[rng.random(shape) < 0.3] = np.nan
    sigma[rng.random(shape) < 0.1] = 0.0
    expected = []  # (sigma, v, u) of each cell's first lowest-sigma valid pixel in raster order
    for v0 in range(0, Hs, cell):
        for u0 in range(0, Ws, cell):
            best = None
            for v in range(v0, min(v0 + cell, Hs)):
                for u in range(u0, min(u0 + cell, Ws)):
                    if np.isfinite(depth[v, u]) and sigma[v, u] > 0 and (best is None or sigma[v, u] < best[0]):
                        best = (sigma[v, u], v, u)
            if best is not None:
                expected.append(best)
    p, s = select_depth_points(depth, sigma, K, len(expected) + 5, cell_px=cell)
    assert len(p) == len(expected)
    vi = np.rint(p[:, 1] / p[:, 2] * K[1, 1] + K[1, 2]).astype(int)
    ui = np.rint(p[:, 0] / p[:, 2] * K[0, 0] + K[0, 2]).astype(int)
    assert sorted(zip(vi.tolist(), ui.tolist())) == sorted((v, u) for _, v, u in expected)
    assert np.all(np.diff(s) >= 0) and np.allclose(sigma[vi, ui], s)

def test_frame_to_map_pulls_a_keyframe_back_and_needs_covisibility(o2p_room):
    msg, renderer = o2p_room
    T_true = view(2.0)  # a view whose points constrain all three translations (1.3 sees mostly one wall)
    stamps = {5: 5 * S}
    for covisible in (False, True):
        terms = OccupancyTerms(O2PConfig(enabled=True))
        for t in range(1, 4):  # frames during submap 0's life
            terms.note_frame(t * S, np.arange(0, 50))
        terms.add_field(msg)
        terms.note_frame(5 * S, np.arange(40, 90) if covisible else np.arange(100, 150))
        assert terms.add_depth(5 * S, renderer.render(K, W, H, T_true), np.full((H, W), 0.03, np.float32), K, np.eye(4)) == 200
        values = gtsam.Values()
        values.insert(X(5), gtsam.Pose3(perturbed(T_true, 3)))
        fs = terms.factors(stamps, values)
        if not covisible:
            assert fs == [] and terms.counts["frame_to_map_no_target"] == 1
            continue
        assert len(fs) == 1 and terms.counts["frame_to_map"] == 1
        assert len(terms.factors(stamps, values)) == 1 and terms.counts["frame_to_map"] == 1  # kept, not rebuilt
        rot, tr = err(solve(fs, values).atPose3(X(5)).matrix(), T_true)
        assert rot < 0.3 and tr < 0.01
        assert terms.factors({}, gtsam.Values()) == []  # the state left the window: its factor goes


def map_to_map_term(o2p_room, cfg=None, expect_term=True):
    """Submap 0 = the mapped o2p_room (T_WM = I, created at 1 s, anchored on keyframe state 1 at P_o); submap 1
    created at 4 s, anchored on state 7, integrated at the estimate T_est of its anchor (true pose T_true):
    its points are right in M_1, its pose is off by 2 deg / 4 cm. Returns the queued term and the poses."""
    msg, renderer = o2p_room
    P_o, T_true = view(0.5), view(3.0)
    T_est = perturbed(T_true, 8)
    published = {1 * S: (1, P_o), 4 * S: (7, T_est)}  # keyframe poses as the mapping saw them
    terms = OccupancyTerms(cfg or O2PConfig(enabled=True, frame_to_map=False, map_to_map=True, effective_points=0),
                           anchoring=Anchors(published))  # eq. 7 uncapped
    for t in range(1, 4):
        terms.note_frame(t * S, np.arange(0, 50))
    terms.add_field(msg)
    p_M, sig = select_depth_points(renderer.render(K, W, H, view(0.5)), np.full((H, W), 0.03, np.float32), K, 1000)
    terms.add_submap_points(0, p_M, sig)  # submap 0 closes: bound to its anchor, no older submap to align to
    assert terms.pop_map_to_map() == [] and terms.counts["map_to_map_no_target"] == 1
    for t in range(4, 7):
        terms.note_frame(t * S, np.arange(30, 80))
    terms.add_field(field_message(Submap(1, T_est, 4 * S, BlockStore(0.025), ChunkMesher(4)), msg.l_min))
    p_M, sig = select_depth_points(renderer.render(K, W, H, T_true), np.full((H, W), 0.03, np.float32), K, 1000)
    terms.add_submap_points(1, p_M, sig)
    out = terms.pop_map_to_map()
    if not expect_term:
        assert out == [] and terms.counts["map_to_map_no_target"] == 2
        return None
    assert len(out) == 1 and terms.counts["map_to_map"] == 1 and terms.pop_map_to_map() == []
    return out[0], P_o, T_true, T_est


@pytest.mark.parametrize("gap_s", [0.9, 1.1])
def test_map_to_map_target_gap(o2p_room, gap_s):
    # submap 0 holds frames 1-3 s, submap 1 begins at 4 s: 1 s apart, so a target with a 0.9 s gap, none with 1.1 s
    cfg = O2PConfig(enabled=True, frame_to_map=False, map_to_map=True, effective_points=0, map_target_gap_s=gap_s)
    got = map_to_map_term(o2p_room, cfg, expect_term=gap_s < 1.0)
    assert (got is not None) == (gap_s < 1.0)
    with pytest.raises(ValueError):
        O2PConfig(map_target_gap_s=-1.0).check()


def test_map_to_map_term_binds_both_submaps_to_their_anchor_keyframes(o2p_room):
    term, P_o, T_true, T_est = map_to_map_term(o2p_room)
    assert (term.submap, term.target, term.state_m, term.state_o) == (1, 0, 7, 1)
    assert np.allclose(term.T_KM_m, np.eye(4)) and np.allclose(term.T_KM_o, inv_T(P_o))
    # at the anchors' true poses the points lie on the o2p_room's surfaces: the factor's error is ~0 there and large
    # at the estimate
    f_true = term.build(X(7), X(1), T_true, P_o)
    v = gtsam.Values()
    v.insert(X(1), gtsam.Pose3(P_o))
    v.insert(X(7), gtsam.Pose3(T_true))
    e_true = f_true.error(v)
    v.update(X(7), gtsam.Pose3(T_est))
    assert e_true < 0.05 * f_true.error(v)
    # without a loop closer (no anchor binding) the term is counted, not built
    terms = OccupancyTerms(O2PConfig(enabled=True, map_to_map=True))
    terms.add_field(o2p_room[0])
    terms.add_submap_points(0, np.zeros((5, 3)), np.full(5, 0.03))
    assert terms.pop_map_to_map() == [] and terms.counts["map_to_map_no_pose_graph"] == 1


def test_submap_point_pool_keeps_spread_lowest_sigma_points_in_the_submap_frame(o2p_room):
    _, renderer = o2p_room
    Wf, Hf = 320, 240
    Kf = intrinsics(Wf, Hf)
    T_WM = view(0.5)
    pool = SubmapPointPool(max_points=400, per_frame=150)
    for a in (0.5, 1.0, 1.5, 2.0):
        T_WC = view(a)
        d = renderer.render(Kf, Wf, Hf, T_WC)
        n = pool.add(3, d, (0.01 * d**2).astype(np.float32), Kf, inv_T(T_WM) @ T_WC)
    assert n == 400
    p_M, s = pool.pop(3)
    assert pool.pop(3) is None
    # the points lie on the o2p_room's surfaces: their distance to the mesh in world is ~0
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(room_scene()))
    p_W = p_M @ T_WM[:3, :3].T + T_WM[:3, 3]
    assert np.percentile(scene.compute_distance(o3d.core.Tensor(p_W.astype(np.float32))).numpy(), 99) < 1e-3
    # spread: every 10 cm cube that any frame's candidates reached keeps a point (here > 100 cubes)
    assert len(np.unique(np.floor(p_M / 0.1), axis=0)) > 100


def test_submap_points_message_round_trip():
    from shared import messages as m
    from shared.codec import decode, encode

    rng = np.random.default_rng(0)
    msg = m.SubmapPoints(header=m.Header(stamp_ns=5, frame_id="M2"), submap_id=2,
                         points_M=rng.normal(size=(7, 3)).astype(np.float32), sigma=np.full(7, 0.02, np.float32))
    back = decode(encode(msg))
    assert back.submap_id == 2 and np.array_equal(back.points_M, msg.points_M) and np.array_equal(back.sigma, msg.sigma)


def test_depth_between_keyframes_attaches_to_the_nearest_state(o2p_room):
    """Depth at 5.1 s, window state at 5.0 s: points move into the state's frame by the estimates' relative
    pose, and the factor still pulls the state onto the map (exact stamps only: no factor)."""
    msg, renderer = o2p_room
    T_k = view(2.0)
    T_d = T_k @ make_T(so3_exp(np.array([0.0, 0.02, 0.0])), np.array([0.05, 0.0, 0.02]))  # 0.1 s of motion
    T_k_est = perturbed(T_k, 5)
    T_d_est = T_k_est @ inv_T(T_k) @ T_d  # odometry-consistent estimate of the depth frame
    for attach_ms, expect, at_add in ((0.0, 0, False), (150.0, 1, False), (150.0, 1, True)):
        terms = OccupancyTerms(O2PConfig(enabled=True, attach_tolerance_ms=attach_ms))
        terms.note_frame(1 * S, np.arange(0, 50))
        terms.add_field(msg)
        terms.note_frame(5 * S, np.arange(10, 60))
        values = gtsam.Values()
        values.insert(X(5), gtsam.Pose3(T_k_est))
        window = ({5: 5 * S}, values) if at_add else ()  # at add time: estimates of the same solve
        terms.add_depth(5 * S + S // 10, renderer.render(K, W, H, T_d), np.full((H, W), 0.03, np.float32), K,
                        np.eye(4), T_d_est, *window)
        if at_add:  # a later solve moves the state: the attached points move with it
            values.update(X(5), gtsam.Pose3(perturbed(T_k_est, 9, 0.5, 0.01)))
        fs = terms.factors({5: 5 * S}, values)
        assert len(fs) == expect
        if expect:
            assert terms.counts["frame_to_map_attached"] == 1
            rot, tr = err(solve(fs, values).atPose3(X(5)).matrix(), T_k)
            assert rot < 0.3 and tr < 0.01


def test_target_state_leaving_the_window_holds_the_submap_fixed(o2p_room):
    """Submap 0 anchored on window state 1: the factor acts on both poses; when state 1 leaves the window the
    factor stays (submap held at its T_WM) instead of referring to a missing key."""
    msg, renderer = o2p_room
    T_true = view(2.0)
    terms = OccupancyTerms(O2PConfig(enabled=True))
    for t in range(1, 4):
        terms.note_frame(t * S, np.arange(0, 50))
    terms.add_field(msg)  # created at 1 s, T_WM = identity
    terms.note_frame(5 * S, np.arange(10, 60))
    terms.add_depth(5 * S, renderer.render(K, W, H, T_true), np.full((H, W), 0.03, np.float32), K, np.eye(4))
    values = gtsam.Values()
    values.insert(X(1), gtsam.Pose3(np.eye(4)))
    values.insert(X(5), gtsam.Pose3(perturbed(T_true, 4)))
    fs = terms.factors({1: 1 * S, 5: 5 * S}, values)
    assert len(fs) == 1 and set(fs[0].keys()) == {X(1), X(5)}
    values.erase(X(1))
    fs = terms.factors({5: 5 * S}, values)
    assert len(fs) == 1 and list(fs[0].keys()) == [X(5)] and terms.counts["factor_target_fixed"] == 1
    rot, tr = err(solve(fs, values).atPose3(X(5)).matrix(), T_true)
    assert rot < 0.3 and tr < 0.01


def test_loop_correction_maps_published_depth_and_submaps_into_the_window_frame(o2p_room):
    """With loop closure, depth poses and submap poses arrive in the corrected frame W' = T_W'W W while the
    window lives in W: the factor must pull the state to its true pose in W, not to T_W'W T_true."""
    import dataclasses

    msg, renderer = o2p_room
    C = make_T(so3_exp(np.radians([0.0, 0.0, 5.0])), np.array([0.2, -0.1, 0.05]))  # T_W'W
    T_true = view(2.0)
    T_est = perturbed(T_true, 6, 1.0, 0.02)
    for hooked, dt in ((True, 0), (True, S // 20), (False, 0)):
        terms = OccupancyTerms(O2PConfig(enabled=True), anchoring=Anchors(C=C) if hooked else None)
        for t in range(1, 4):
            terms.note_frame(t * S, np.arange(0, 50))
        terms.add_field(dataclasses.replace(msg, T_WM=C @ np.asarray(msg.T_WM)))  # the map, published in W'
        terms.note_frame(5 * S, np.arange(10, 60))
        values = gtsam.Values()
        values.insert(X(5), gtsam.Pose3(T_est))
        # depth at the state's stamp or 50 ms later (attached by the relative pose), its pose as published (W')
        T_d = T_true @ make_T(np.eye(3), np.array([0.02 * dt / (S // 20), 0.0, 0.0]))
        terms.add_depth(5 * S + dt, renderer.render(K, W, H, T_d), np.full((H, W), 0.03, np.float32), K,
                        np.eye(4), C @ T_est @ inv_T(T_true) @ T_d, {5: 5 * S}, values)
        fs = terms.factors({5: 5 * S}, values)
        if not hooked:  # the map is taken where W' puts it: no factor, or one that pulls the state off
            if fs:
                assert err(solve(fs, values).atPose3(X(5)).matrix(), T_true)[1] > 0.05
            continue
        assert len(fs) == 1 and terms.counts["frame_to_map_attached"] == (1 if dt else 0)
        rot, tr = err(solve(fs, values).atPose3(X(5)).matrix(), T_true)
        assert rot < 0.3 and tr < 0.01


@pytest.mark.parametrize("min_age_s", [1.5, 2.5])
def test_frame_to_map_target_must_be_old_enough(o2p_room, min_age_s):
    # submap 0 was mapped from 1 s to 3 s; the frame at 5 s is 2 s after it: a target with a 1.5 s gap, none with 2.5 s
    msg, renderer = o2p_room
    T_true = view(2.0)
    terms = OccupancyTerms(O2PConfig(enabled=True, min_target_age_s=min_age_s))
    for t in range(1, 4):
        terms.note_frame(t * S, np.arange(0, 50))
    terms.add_field(msg)
    terms.note_frame(5 * S, np.arange(40, 90))
    terms.add_depth(5 * S, renderer.render(K, W, H, T_true), np.full((H, W), 0.03, np.float32), K, np.eye(4))
    values = gtsam.Values()
    values.insert(X(5), gtsam.Pose3(perturbed(T_true, 3)))
    fs = terms.factors({5: 5 * S}, values)
    if min_age_s < 2.0:
        assert len(fs) == 1 and terms.counts["frame_to_map_recent_targets_skipped"] == 0
    else:
        assert fs == [] and terms.counts["frame_to_map_recent_targets_skipped"] == 1
        assert terms.counts["frame_to_map_no_target"] == 1
    with pytest.raises(ValueError):
        O2PConfig(min_target_age_s=-1.0).check()


def test_a_verified_loop_makes_the_old_submap_covisible(o2p_room):
    # the frame at 20 s sees none of submap 0's landmark ids (a revisit: the tracker made new ones), so there is
    # no target; the loop closer's match of that keyframe to submap 0's landmarks makes submap 0 its o(k)
    msg, renderer = o2p_room
    T_true = view(2.0)
    for loop in (False, True):
        terms = OccupancyTerms(O2PConfig(enabled=True))
        for t in range(1, 4):
            terms.note_frame(t * S, np.arange(0, 50))
        terms.add_field(msg)
        terms.note_frame(20 * S, np.arange(500, 550))
        if loop:
            terms.note_loop(20 * S, np.arange(10, 40))
        terms.add_depth(20 * S, renderer.render(K, W, H, T_true), np.full((H, W), 0.03, np.float32), K, np.eye(4))
        values = gtsam.Values()
        values.insert(X(9), gtsam.Pose3(perturbed(T_true, 3)))
        fs = terms.factors({9: 20 * S}, values)
        if loop:
            assert len(fs) == 1 and terms.counts["frames_with_loop_landmarks"] == 1
            rot, tr = err(solve(fs, values).atPose3(X(9)).matrix(), T_true)
            assert rot < 0.3 and tr < 0.01
        else:
            assert fs == [] and terms.counts["frame_to_map_no_target"] == 1
