"""Saved maps without transport: the sparse map file (round trip, refusals), combining maps, the pose graph with a
saved map's fixed nodes, and finding one map in another (map merge) on a simulated scene with a known offset."""

import json

import numpy as np
import pytest

import vio_sim as sim
from services.backend.loop.config import LoopConfig
from services.backend.loop.map_merge import align_maps
from services.backend.loop.pose_graph import LoopConstraint, PoseGraph
from services.backend.loop.saved_map import (LOOP, ODOMETRY, SparseMapError, build_map, concatenate, load_sparse,
                                             save_sparse)
from services.backend.loop.verification import FeatureSet
from services.backend.loop.vocabulary import DEFAULT_PATH, Vocabulary
from shared.geometry import inv_T, so3_exp, so3_log

pytestmark = pytest.mark.unit


def _T(rotvec, t):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = so3_exp(np.asarray(rotvec, float)), t
    return T


def _scene_map(T_frame=np.eye(4), seed=0, every=3, t_end=12.0, meta_extra=None):
    """A sparse map of the simulated flight: keyframes every ``every`` frames at ground-truth poses, each with the
    landmarks it sees (fixed random ORB-like codes, a few bits flipped), all in the frame ``T_frame`` (T_frame_gt)."""
    rng = np.random.default_rng(seed)
    tr, pts, cams = sim.Trajectory(), sim.landmarks_cylinder(600, seed=6), sim.rig(2)
    codes = np.random.default_rng(99).integers(0, 256, (len(pts), 32), dtype=np.uint8)
    times = np.arange(0.5, t_end, 0.1)[::every]
    kfs = []
    for k, (t, T) in enumerate(zip(times, tr.T_WS(times))):
        ids, c, uv = sim.observe(T, pts, cams, 0.5, rng, 30)
        flips = np.packbits(rng.random((len(ids), 256)) < 0.03, axis=1)
        fs = FeatureSet(ids.astype(np.int64), c.astype(np.int64), uv, codes[ids] ^ flips)
        xy = np.array([cams[ci].undistort(u[None])[0] for ci, u in zip(c, uv)]).reshape(-1, 2)
        p = pts[ids] @ T_frame[:3, :3].T + T_frame[:3, 3]
        kfs.append((k, int(t * 1e9), T_frame @ T, fs, p, xy))
    edges = [(k, k + 1, inv_T(kfs[k][2]) @ kfs[k + 1][2], np.eye(6) * 1e-4, ODOMETRY) for k in range(len(kfs) - 1)]
    meta = {"cameras": [{"T_SC": c.T_SC.tolist(), "focal_px": float(c.K[0, 0])} for c in cams],
            "sessions": [{"source": f"sim seed {seed}"}], **(meta_extra or {})}
    return build_map(kfs, edges, meta)


def test_sparse_map_round_trip_and_summary(tmp_path):
    m = _scene_map()
    path = save_sparse(m, tmp_path / "map" / "sparse.npz")
    back = load_sparse(path)
    for k in ("keys", "stamps_ns", "T_WS", "feat_offsets", "landmark_ids", "camera_index", "uv", "xy", "descriptors",
              "p_W", "edges", "edge_T", "edge_cov", "edge_kind"):
        assert np.array_equal(getattr(back, k), getattr(m, k), equal_nan=True), k
    fs, p = back.features(3)
    assert len(fs.landmark_ids) == len(p) > 20 and fs.descriptors.shape[1] == 32
    s = back.summary()
    assert s["keyframes"] == len(m) and s["odometry_edges"] == len(m) - 1 and s["loop_edges"] == 0
    assert s["landmarks"] == len(np.unique(m.landmark_ids)) and s["path_length_m"] > 1.0
    assert not list((tmp_path / "map").glob(".*.tmp"))  # the atomic writer left nothing behind


def test_unreadable_sparse_maps_are_refused_clearly(tmp_path):
    bad = tmp_path / "sparse.npz"
    bad.write_bytes(b"not a map")
    with pytest.raises(SparseMapError, match="not a readable sparse map"):
        load_sparse(bad)
    m = _scene_map(t_end=3.0)
    m.meta["format"] = "something-else/9"
    np.savez(tmp_path / "other.npz", meta=np.frombuffer(json.dumps(m.meta).encode(), np.uint8))
    with pytest.raises(SparseMapError, match="format"):
        load_sparse(tmp_path / "other.npz")
    with pytest.raises(FileNotFoundError):
        load_sparse(tmp_path / "missing.npz")


def test_concatenate_moves_the_second_map_and_keeps_ids_apart():
    a, b = _scene_map(t_end=4.0), _scene_map(t_end=4.0, seed=1)
    T_ab = _T([0, 0, 0.7], [2.0, -1.0, 0.3])
    link = [(int(a.keys[2]), int(b.keys[5]), np.eye(4), np.eye(6) * 1e-3, LOOP)]
    m = concatenate(a, b, T_ab, link)
    assert len(m) == len(a) + len(b) and len(np.unique(m.keys)) == len(m)
    assert np.allclose(m.T_WS[len(a):], np.einsum("ij,njk->nik", T_ab, b.T_WS))
    nb = len(b.landmark_ids)
    assert np.allclose(m.p_W[-nb:], b.p_W @ T_ab[:3, :3].T + T_ab[:3, 3])
    assert not set(m.landmark_ids[:len(a.landmark_ids)]) & set(m.landmark_ids[-nb:])  # b's landmarks are new ones
    assert m.edges[-1].tolist() == [int(a.keys[2]), int(m.keys[len(a) + 5])] and m.edge_kind[-1] == LOOP
    assert len(m.meta["sessions"]) == 2
    with pytest.raises(SparseMapError, match="vocabularies"):
        concatenate(_scene_map(t_end=2.0, meta_extra={"vocabulary": {"sha1": "x"}}),
                    _scene_map(t_end=2.0, meta_extra={"vocabulary": {"sha1": "y"}}))


def test_pose_graph_moves_the_session_onto_fixed_map_nodes():
    """A session chain estimated in its own frame W, a saved map's nodes fixed in M = T_MW W: loops between them
    (after align_session from one match) bring every session node to its map-frame pose."""
    rng = np.random.default_rng(1)
    T_MW = _T([0.0, 0.0, 1.1], [3.0, -2.0, 0.4])
    truth = [_T([0, 0, 0.2 * k], [np.cos(0.2 * k), np.sin(0.2 * k), 0.1 * k]) for k in range(12)]  # in M
    g = PoseGraph(attitude_sigma_rad=np.deg2rad(0.2))
    for k, T in enumerate(truth[:6]):
        g.add_fixed_node(1000 + k, T)
    odom = [inv_T(T_MW) @ T for T in truth]  # the session's own estimate, in W (no drift)
    for k, T in enumerate(odom):
        noisy = T.copy()
        noisy[:3, 3] += rng.normal(0, 0.002, 3)
        g.add_node(k, noisy, None if k == 0 else np.eye(6) * 1e-5)
    g.optimise()
    assert np.linalg.norm(g.estimate[11][:3, 3] - truth[11][:3, 3]) > 1.0  # still in its own frame
    g.align_session(T_MW)  # what one verified match says
    for k in range(0, 6, 2):
        g.add_loop(LoopConstraint(1000 + k, k, np.eye(4), np.eye(6) * 1e-4))
    g.optimise()
    err = [np.linalg.norm(g.estimate[k][:3, 3] - truth[k][:3, 3]) for k in range(12)]
    assert max(err) < 0.02, err
    assert np.allclose(g.estimate[1002], truth[2], atol=1e-3)  # the map did not move
    assert np.allclose(g.correction(), T_MW, atol=0.02)


def test_align_maps_finds_the_offset_between_two_maps_of_one_place():
    voc = Vocabulary.load(DEFAULT_PATH)
    T_ab = _T([0.0, 0.0, -0.6], [1.5, 2.0, -0.2])  # map b's frame in map a's
    a = _scene_map(seed=0, every=5)
    b = _scene_map(T_frame=inv_T(T_ab), seed=3, every=5)
    res = align_maps(a, b, voc, LoopConfig())
    assert res.T_ab is not None and res.agreeing >= 2, res
    assert np.linalg.norm(res.T_ab[:3, 3] - T_ab[:3, 3]) < 0.05
    assert np.allclose(res.T_ab[:3, :3], T_ab[:3, :3], atol=0.01)
    for k_a, k_b, T_rel, cov, kind in res.links:  # each link is the true relative pose of two keyframes
        i, j = int(np.flatnonzero(a.keys == k_a)[0]), int(np.flatnonzero(b.keys == k_b)[0])
        assert np.linalg.norm((inv_T(a.T_WS[i]) @ T_ab @ b.T_WS[j])[:3, 3] - T_rel[:3, 3]) < 0.05
    # a map of another place (other landmarks and codes) is not found in a
    far = _scene_map(seed=4, every=10)
    far.descriptors[:] = np.random.default_rng(5).integers(0, 256, far.descriptors.shape, dtype=np.uint8)
    assert align_maps(a, far, voc, LoopConfig()).T_ab is None


def test_a_map_saved_by_the_loop_closer_places_a_new_view_after_the_file_round_trip(tmp_path):
    """What relocalisation in a saved map rests on, through the file: keyframes made by the loop closer in a window
    frame W (a yaw and a shift from the truth) are saved, loaded by a second closer, and a view the first session
    never had (half a keyframe interval later, from another session's frame) is matched to them by PnP at its true
    pose in W. Also checked: each saved landmark projects onto its saved feature at its keyframe's saved pose."""
    from shared.vio.cameras import VioCamera
    from services.backend.loop.history import KeyframeRecord
    from services.backend.loop.loop_closer import LoopCloser
    from services.backend.loop.map_session import PRIOR_KEY_BASE

    rng = np.random.default_rng(3)
    tr, pts, cams = sim.Trajectory(), sim.landmarks_cylinder(600, seed=6), sim.rig(2)
    codes = rng.integers(0, 256, (len(pts), 32), dtype=np.uint8)
    bcams = [VioCamera(c.T_SC, c.undistort, c.K[0, 0]) for c in cams]
    T_WG = _T([0.0, 0.0, 0.8], [1.5, -0.5, 0.2])  # the first session's window frame W from the truth
    cfg = LoopConfig(min_inliers=15)
    first = LoopCloser(cfg, bcams)

    def features(T_GS):
        ids, c, uv = sim.observe(T_GS, pts, cams, 0.5, rng, 40)
        flips = np.packbits(rng.random((len(ids), 256)) < 0.03, axis=1)
        return FeatureSet(ids.astype(np.int64), c.astype(np.int64), uv, codes[ids] ^ flips)

    times = np.arange(0.5, 12.0, 0.3)
    for k, (t, T_GS) in enumerate(zip(times, tr.T_WS(times))):
        stamp, fs = int(t * 1e9), features(T_GS)
        first.add_keyframe_features(stamp, fs)
        seen = {int(i): T_WG[:3, :3] @ pts[i] + T_WG[:3, 3] for i in fs.landmark_ids}
        first.add_record(KeyframeRecord(k, stamp, T_WG @ T_GS, np.zeros(3), None, {i: [] for i in seen}, seen))
    saved = load_sparse(save_sparse(first.sparse_map({"source": "sim"}), tmp_path / "sparse.npz"))
    assert len(saved) == len(times)
    for i in range(len(saved)):
        fs, p_W = saved.features(i)
        for c, cam in enumerate(cams):
            sel = (fs.camera_index == c) & np.isfinite(p_W[:, 0])
            T_CW = inv_T(saved.T_WS[i] @ cam.T_SC)
            uv = cam.project(p_W[sel] @ T_CW[:3, :3].T + T_CW[:3, 3])
            assert np.abs(uv - fs.uv[sel]).max() < 3.0, i  # 0.5 px noise
    second = LoopCloser(LoopConfig(min_inliers=15), bcams)
    second.load_prior(saved)
    t_new = times[14] + 0.15
    T_GS_new = tr.T_WS(np.array([t_new]))[0]
    found = second.add_keyframe_features(int(t_new * 1e9), features(T_GS_new))
    assert found and found[0].old_state >= PRIOR_KEY_BASE, dict(second.counts)
    err = inv_T(T_WG @ T_GS_new) @ found[0].T_WS_query
    assert np.linalg.norm(err[:3, 3]) < 0.03 and np.degrees(np.linalg.norm(so3_log(err[:3, :3]))) < 0.5
