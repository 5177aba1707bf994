"""Viewer scene logic without viser or Zenoh: change tracking, trajectories, colours, export, throttling."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from services.viewer.colors import colormap, depth_image, height_colors, submap_color
from services.viewer.config import ViewerConfig
from services.viewer.scene_model import ViewerModel
from services.viewer.stats_panel import stats_markdown
from services.viewer.submaps import SubmapStore, write_ply
from services.viewer.tracks import CHUNK, ChunkedTrajectory, GroundTruthOverlay, KeyframeTrack, LandmarkBuffer
from shared import messages as m
from shared.camera import CameraCalib, CameraModel
from shared.euroc import PoseSeries
from shared.geometry import make_T, so3_exp, transform_points


def H(t: int = 0, frame: str = "W") -> m.Header:
    return m.Header(stamp_ns=t, seq=0, frame_id=frame)


def box_mesh(sid: int, T_WM: np.ndarray, size: float = 1.0, colors: bool = False) -> m.SubmapMesh:
    tm = trimesh.creation.box(extents=(size, size, size))
    v = np.asarray(tm.vertices, np.float32)
    vc = (np.arange(len(v) * 3) % 255).astype(np.uint8).reshape(-1, 3) if colors else np.zeros((0, 3), np.uint8)
    return m.SubmapMesh(header=H(sid), submap_id=sid, T_WM=T_WM, vertices_M=v,
                        faces=np.asarray(tm.faces, np.int32), vertex_colors=vc)


def pose(rotvec=(0, 0, 0), t=(0, 0, 0)) -> np.ndarray:
    return make_T(so3_exp(np.asarray(rotvec, float)), np.asarray(t, float))


def state(t_ns: int, T_WS: np.ndarray) -> m.EstimatorState:
    return m.EstimatorState(header=H(t_ns), T_WS=T_WS, v_W=np.zeros(3), gyro_bias=np.zeros(3), acc_bias=np.zeros(3),
                            covariance=np.eye(15))


# ---------------------------------------------------------------------------- submaps


def test_only_changed_submaps_are_resent_and_pose_updates_only_move():
    store = SubmapStore("submap")
    a, b = box_mesh(0, pose()), box_mesh(1, pose(t=(2, 0, 0)))
    assert store.apply(a) == "mesh" and store.apply(b) == "mesh"
    ch = store.take_changes()
    assert ch.meshes == (0, 1) and ch.poses == () and ch.removed == ()
    assert not store.take_changes()
    assert store.apply(a) == "unchanged"  # identical re-send: nothing to draw
    assert not store.take_changes()
    moved = box_mesh(1, pose((0, 0, 0.3), (2, 1, 0)))
    assert store.apply(moved) == "pose"
    ch = store.take_changes()
    assert ch.meshes == () and ch.poses == (1,)
    np.testing.assert_allclose(store.entries[1].T_WM, moved.T_WM)
    bigger = box_mesh(0, pose(), size=2.0)  # new geometry: mesh re-sent
    assert store.apply(bigger) == "mesh"
    assert store.take_changes().meshes == (0,)
    store.set_color_mode("height")  # colours are baked in: every mesh re-sent
    assert store.take_changes().meshes == (0, 1)
    store.remove(0)
    assert store.take_changes().removed == (0,)


def test_malformed_meshes_are_rejected():
    store = SubmapStore()
    good = box_mesh(0, pose())
    bad_faces = box_mesh(0, pose())
    object.__setattr__(bad_faces, "faces", bad_faces.faces + 8)  # past the 8 vertices
    bad_pose = box_mesh(0, np.full((4, 4), np.nan))
    bad_verts = box_mesh(0, pose())
    object.__setattr__(bad_verts, "vertices_M", np.where(bad_verts.vertices_M > 0, np.inf, 0).astype(np.float32))
    for msg in (bad_faces, bad_pose, bad_verts):
        with pytest.raises(ValueError):
            store.apply(msg)
    assert not store.entries and store.apply(good) == "mesh"


def test_height_mode_recolours_only_after_a_real_height_change():
    store = SubmapStore("height", (-1.0, 3.0))
    store.apply(box_mesh(0, pose()))
    ch = store.take_changes()
    store.colors(store.entries[0])  # drawn at this pose
    store.apply(box_mesh(0, pose(t=(0.5, 0.0, 0.01))))  # sideways, 1 cm up: just move
    assert store.take_changes().poses == (0,)
    store.apply(box_mesh(0, pose(t=(0.5, 0.0, 0.5))))  # 0.5 m up: colours change
    ch = store.take_changes()
    assert ch.meshes == (0,) and ch.poses == ()


def test_colour_modes_and_height_colours_follow_world_z():
    store = SubmapStore("submap", (0.0, 1.0))
    store.apply(box_mesh(3, pose(t=(0, 0, 0.5)), colors=True))
    e = store.entries[3]
    np.testing.assert_array_equal(store.colors(e), np.broadcast_to(submap_color(3), (8, 3)))
    store.set_color_mode("uncertainty")
    np.testing.assert_array_equal(store.colors(e), e.vertex_colors)
    store.set_color_mode("height")
    z_W = transform_points(e.T_WM, e.vertices_M.astype(float))[:, 2]
    np.testing.assert_array_equal(store.colors(e), height_colors(z_W, (0.0, 1.0)))
    # a mesh without vertex colours falls back to its submap colour in 'uncertainty' mode
    store.apply(box_mesh(4, pose()))
    store.set_color_mode("uncertainty")
    np.testing.assert_array_equal(store.colors(store.entries[4])[0], submap_color(4))
    with pytest.raises(ValueError):
        store.set_color_mode("rainbow")


def test_colour_maps():
    cols = np.stack([submap_color(i) for i in range(10)]).astype(float)
    d = np.linalg.norm(cols[:, None] - cols[None], axis=2)
    assert d[~np.eye(10, dtype=bool)].min() > 20  # distinct colours for neighbouring submaps
    c = colormap(np.array([0.0, 1.0, np.nan, 5.0]), 0.0, 1.0)
    assert c[0, 2] > c[0, 0] and c[1, 0] > c[1, 2]  # turbo: low is blue, high is red
    np.testing.assert_array_equal(c[2], [0, 0, 0])  # NaN -> black
    np.testing.assert_array_equal(c[3], c[1])  # clipped
    img = depth_image(np.array([[0.5, 7.0]], np.float32), (0.3, 8.0))
    assert img.shape == (1, 2, 3) and img[0, 0, 0] > img[0, 0, 2] and img[0, 1, 2] > img[0, 1, 0]  # near warm, far cold
    with pytest.raises(ValueError):
        colormap(np.zeros(3), 1.0, 1.0)


def test_world_mesh_export_places_submaps_by_their_pose(tmp_path):
    store = SubmapStore("submap")
    T0, T1 = pose((0.1, 0.2, 0.3), (1, 2, 3)), pose((0, 0, 1.0), (-1, 0, 0.5))
    a, b = box_mesh(0, T0), box_mesh(1, T1, size=0.5)
    store.apply(a)
    store.apply(b)
    v, f, c = store.world_mesh()
    path = write_ply(tmp_path / "w.ply", v, f, c)
    back = trimesh.load(path, process=False)
    expect = np.concatenate([transform_points(T0, a.vertices_M.astype(float)), transform_points(T1, b.vertices_M.astype(float))])
    np.testing.assert_allclose(back.vertices, expect, atol=1e-5)
    np.testing.assert_array_equal(back.faces, np.concatenate([a.faces, b.faces + len(a.vertices_M)]))
    np.testing.assert_array_equal(back.visual.vertex_colors[:8, :3], np.broadcast_to(submap_color(0), (8, 3)))
    with pytest.raises(ValueError):
        write_ply(tmp_path / "bad.ply", v, f + 1000)


# ---------------------------------------------------------------------------- trajectories, landmarks, GT


def test_chunked_trajectory_resends_only_the_tail_and_stays_bounded():
    traj = ChunkedTrajectory(max_points=2 * CHUNK)
    pts = np.cumsum(np.random.default_rng(0).normal(size=(CHUNK + 10, 3)), axis=0)
    for i, p in enumerate(pts):
        assert traj.append(i + 1, p)
    changed, removed = traj.take_changes()
    assert sorted(changed) == [0, 1] and removed == ()
    np.testing.assert_allclose(changed[0], pts[:CHUNK + 1])  # chunk 0 ends at chunk 1's first point: continuous
    np.testing.assert_allclose(changed[1], pts[CHUNK:])
    traj.append(10_000, np.zeros(3))
    changed, _ = traj.take_changes()
    assert list(changed) == [1]  # the full chunk is never sent again
    assert not traj.append(5, np.ones(3)) and traj.dropped_out_of_order == 1
    for i in range(3 * CHUNK):
        traj.append(20_000 + i, np.full(3, i, float))
    changed, removed = traj.take_changes()
    assert 0 in removed and len(traj) <= 3 * CHUNK
    t, p = traj.all_points()
    assert np.all(np.diff(t) > 0) and len(t) == len(traj)
    np.testing.assert_allclose(traj.latest, np.full(3, 3 * CHUNK - 1))


def test_keyframe_track_takes_newest_pose_per_id_in_time_order():
    kf = KeyframeTrack()
    T = np.stack([pose(t=(i, 0, 0)) for i in range(3)])
    kf.update(np.array([0, 1, 2]), np.array([10, 20, 30]), T)
    T2 = np.stack([pose(t=(5, 5, 5)), pose(t=(9, 0, 0))])
    kf.update(np.array([1, 3]), np.array([20, 40]), T2)
    np.testing.assert_allclose(kf.take(), [[0, 0, 0], [5, 5, 5], [2, 0, 0], [9, 0, 0]])
    assert kf.take() is None


def test_landmark_buffer_is_bounded_drops_nan_and_keeps_newest_per_id():
    lm = LandmarkBuffer(capacity=5)
    lm.add(np.array([1, 2, 3]), np.array([[1, 0, 0], [np.nan, 0, 0], [3, 0, 0]], float))
    lm.add(np.array([1, 4, 5, 6]), np.array([[1, 1, 1], [4, 0, 0], [5, 0, 0], [6, 0, 0]], float))
    p = lm.positions()
    assert len(p) == 5  # 6 valid observations in a ring of 5: the oldest (id 1) fell out; ids 1, 3, 4, 5, 6 remain
    assert sorted(map(tuple, p.tolist())) == [(1, 1, 1), (3, 0, 0), (4, 0, 0), (5, 0, 0), (6, 0, 0)]
    lm.add(np.array([3, 3]), np.array([[7, 7, 7], [8, 8, 8]], float))  # the newest observation of an id wins
    assert [8, 8, 8] in lm.positions().tolist() and [7, 7, 7] not in lm.positions().tolist()


def test_model_draws_the_estimators_landmarks():
    model = ViewerModel(ViewerConfig(max_landmarks=100))
    assert model.take_update(0.0).landmarks_W is None
    p = np.array([[1.0, 2, 3], [4, 5, 6], [np.nan, 0, 0]])
    model.apply(m.Landmarks(header=H(10), ids=np.array([7, 8, 9]), p_W=p, num_observations=np.full(3, 2, np.int32),
                            last_seen_ns=np.full(3, 10, np.int64)), 0.0)
    up = model.take_update(0.1)
    assert sorted(map(tuple, up.landmarks_W.tolist())) == [(1, 2, 3), (4, 5, 6)]  # the non-finite one is not drawn
    assert model.take_update(0.2).landmarks_W is None  # unchanged
    # a later window moves landmark 8 and adds 10; 7 (out of the window now) keeps its last position
    model.apply(m.Landmarks(header=H(20), ids=np.array([8, 10]), p_W=np.array([[4.0, 5, 7], [0, 0, 1]]),
                            num_observations=np.full(2, 3, np.int32), last_seen_ns=np.full(2, 20, np.int64)), 0.3)
    up = model.take_update(0.4)
    assert sorted(map(tuple, up.landmarks_W.tolist())) == [(0, 0, 1), (1, 2, 3), (4, 5, 7)]
    assert model.counts["landmarks"] == 2 and "**landmarks** 3" in up.status_md


def test_ground_truth_overlay_is_aligned_onto_the_estimate():
    rng = np.random.default_rng(1)
    t = np.arange(50, dtype=np.int64) * 50_000_000
    p_est = np.cumsum(rng.normal(size=(50, 3)), axis=0)
    T_GW = pose((0.0, 0.0, 1.2), (3.0, -2.0, 0.5))  # GT frame differs from the estimator's W
    p_gt = transform_points(T_GW, p_est)
    gt = PoseSeries(t, p_gt, np.tile([1.0, 0, 0, 0], (50, 1)))
    ov = GroundTruthOverlay(gt, "se3")
    assert ov.take() is None  # nothing to draw before it is aligned
    assert ov.realign(t, p_est)
    np.testing.assert_allclose(ov.take(), p_est, atol=1e-6)
    assert not ov.realign(t[:60], p_est)  # not grown enough: no re-alignment
    assert GroundTruthOverlay(gt, "none").take() is not None


# ---------------------------------------------------------------------------- the model


def test_model_frusta_images_throttle_and_status():
    T_SC = pose((0.1, -0.2, 0.05), (0.05, 0.01, 0.0))
    cam = CameraCalib("cam0", CameraModel(752, 480, 458.0, 457.0, 367.0, 248.0), T_SC)
    model = ViewerModel(ViewerConfig(image_rate_hz=5.0), cameras=[cam])
    img = np.tile(np.arange(752, dtype=np.uint8), (480, 1))
    n_images = 0
    for i in range(40):  # 2 s of 20 Hz frames and states, drawn at 20 Hz
        now = i * 0.05
        T_WS = pose((0, 0, 0.01 * i), (0.1 * i, 0, 1))
        model.apply(state(i * 50_000_000, T_WS), now)
        model.apply(m.MultiCameraFrame(header=H(i * 50_000_000, ""), images=(img, img), camera_names=("cam0", "cam1"),
                                       stamps_ns=np.array([i, i], np.int64)), now)
        up = model.take_update(now)
        n_images += up.live_image is not None
        assert up.T_WS is not None
        np.testing.assert_allclose(up.frusta[0].T_WC, T_WS @ T_SC)
        assert math.isclose(up.frusta[0].fov_y_rad, 2 * math.atan(240 / 457.0))
    assert 9 <= n_images <= 11  # 5 Hz of the 20 Hz frames
    assert up.status_md and "40" in up.status_md
    assert model.take_update(2.0).T_WS is None  # nothing new


def test_model_depth_prefers_fused_and_learns_camera_from_depth():
    model = ViewerModel(ViewerConfig(image_rate_hz=100.0))
    d = np.full((4, 6), 2.0, np.float32)
    d[0, 0] = np.nan
    K = np.array([[100.0, 0, 3], [0, 100.0, 2], [0, 0, 1]])
    for src, t in (("stereo", 0.0), ("fused", 0.1), ("stereo", 0.2)):
        model.apply(m.DepthFrame(header=H(0, "cam0"), depth=d, sigma=d * 0.1, K=K, T_WC=np.eye(4), source=src), t)
    up = model.take_update(0.3)
    assert up.depth_source == "fused" and up.depth_rgb.shape == (4, 6, 3)
    np.testing.assert_array_equal(up.depth_rgb[0, 0], [0, 0, 0])
    model.apply(m.DepthFrame(header=H(0, "cam0"), depth=d, sigma=d, K=K, T_WC=np.eye(4), source="stereo"), 5.0)
    assert model.take_update(5.0).depth_source == "stereo"  # fused went silent
    model.apply(state(1, pose()), 5.0)
    fr = model.take_update(5.1).frusta
    assert [f.name for f in fr] == ["cam0"] and math.isclose(fr[0].aspect, 1.5)
    with pytest.raises(ValueError):
        model.apply(state(2, np.full((4, 4), np.nan)))


def test_stats_markdown():
    st = m.ServiceStats(header=H(0, ""), service="depth", uptime_s=1.0, rss_mb=10.0, stage_names=("stereo", "fuse"),
                        stage_count=np.array([10, 10]), stage_rate_hz=np.array([9.5, 9.5]),
                        stage_p50_ms=np.array([80.0, 3.0]), stage_p99_ms=np.array([120.0, 4.0]),
                        stage_budget_ms=np.array([100.0, np.nan]), stage_overruns=np.array([2, 0]),
                        queue_names=("sensors/frame", "estimator/keyframes"), queue_received=np.array([20, 5]),
                        queue_dropped=np.array([3, 1]), queue_depth=np.array([0, 0]))
    md = stats_markdown({"depth": (st, 10.0)}, 11.0)
    row = [r for r in md.splitlines() if r.startswith("| depth")][0]
    assert "| stereo | 9.5 | 80.0 | 120.0 | 100 | 2 | 4 |" in row
    assert "stale" in stats_markdown({"depth": (st, 0.0)}, 10.0)


def test_build_model_uses_the_pipeline_rig_and_real_ground_truth(tmp_path):
    from services.app.cli import main
    from services.app.system_config import load_system_config
    from services.viewer.node import build_model
    from shared.camera import CalibrationError
    from shared.paths import euroc_files

    gt_file = euroc_files("V1_02")["groundtruth"]
    cfg = load_system_config(None, [f"viewer.ground_truth={gt_file}"])
    model = build_model(cfg)  # rig: the real EuRoC calibration (rig.calibration = '')
    assert len(model.ground_truth.gt) > 10000
    model.apply(state(1, pose()))
    fr = model.take_update(0.0).frusta
    assert [f.name for f in fr] == ["cam0", "cam1"]
    assert abs(fr[1].T_WC[:3, 3] - fr[0].T_WC[:3, 3]).max() > 0.1  # the 11 cm stereo baseline
    with pytest.raises(CalibrationError):
        build_model(load_system_config(None, [f"viewer.rig={tmp_path / 'none.yaml'}"]))

    assert main(["viewer", "--set", f"viewer.ground_truth={tmp_path / 'missing.csv'}"]) == 2  # a clear error, no
    # server started
