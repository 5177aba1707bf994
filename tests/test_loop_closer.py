"""Loop closer on simulated VIO (estimator + keyframe history as its marginalisation listener + bag of words + PnP +
pose graph), no transport. Every landmark carries a fixed random ORB-like code, observed with a few flipped bits.

* Revisits of the same place are proposed, verified and accepted, and every accepted loop agrees with the
  ground-truth relative pose (no false loop).
* Relocalisation: the cameras go blank for long enough that the window forgets the map; the IMU alone
  drifts; when the images return, the loop closer ties the new keyframes to the map from before the loss
  and the corrected pose is closer to the ground truth than the drifted one.
"""

import numpy as np
import pytest

import vio_sim as sim
from services.backend.config import BackendConfig
from services.backend.window.estimator import WindowedVioEstimator
from shared.vio.cameras import VioCamera
from services.backend.loop.config import LoopConfig
from services.backend.loop.history import KeyframeHistory, KeyframeRecord
from services.backend.loop.loop_closer import LoopCloser
from services.backend.loop.loop_thread import ThreadedLoopCloser
from services.backend.loop.verification import FeatureSet
from shared.geometry import inv_T, so3_exp

IMU_NOISE = dict(gyro_nd=1.7e-4, acc_nd=2e-3, gyro_rw=1.9e-5, acc_rw=3e-3)


def _run(t_end, blank=(np.inf, np.inf), seed=5, threaded=False, acc_bias=(0.05, -0.03, 0.02), prior=None,
         T_off=np.eye(4), t_start=0.5, cfg=LoopConfig(min_age_s=8.0)):
    """The estimator (initialised at the ground truth moved by ``T_off``, a yaw and a shift: its own frame) and the
    loop closer (localising in the saved map ``prior`` if given) over the simulated flight from ``t_start``."""
    rng = np.random.default_rng(seed)
    tr = sim.Trajectory()
    pts = sim.landmarks_cylinder(600, seed=6)
    codes = rng.integers(0, 256, (len(pts), 32), dtype=np.uint8)
    cams = sim.rig(2)
    bcams = [VioCamera(c.T_SC, c.undistort, c.K[0, 0]) for c in cams]
    closer = LoopCloser(cfg, bcams)
    if prior is not None:
        closer.load_prior(prior)
    runner = ThreadedLoopCloser(closer, synchronous=threaded == "sync") if threaded else None
    hist = KeyframeHistory(listeners=[runner.submit_record if threaded else closer.add_record])
    est = WindowedVioEstimator(BackendConfig(compute_covariance=False), bcams, on_marginalise=[hist])
    st, om, ac = sim.imu(tr, 0.0, t_end + 0.1, 200.0, rng, gyro_bias=(0.002, -0.001, 0.003), acc_bias=acc_bias,
                         **IMU_NOISE)
    t0 = t_start
    T0 = T_off @ tr.T_WS(np.array([t0]))[0]
    est.initialise(int(t0 * 1e9), T0[:3, :3], T_off[:3, :3] @ tr.velocity(np.array([t0]))[0], np.zeros(3),
                   np.zeros(3), static=True, p_W=T0[:3, 3])
    times = np.arange(t0, t_end, 0.1)
    gt = tr.T_WS(times)
    out, j = [], 0
    for i, (t, T) in enumerate(zip(times, gt)):
        stamp = int(round(t * 1e9))
        while j < len(st) and st[j] <= stamp:
            est.add_imu(st[j], om[j], ac[j])
            j += 1
        if blank[0] <= t < blank[1]:
            ids, c, uv = np.zeros(0, np.int64), np.zeros(0, np.int16), np.zeros((0, 2))
        else:
            ids, c, uv = sim.observe(T, pts, cams, 0.7, rng, 30)
        kf = i % 3 == 0
        if kf and len(ids):
            flips = np.packbits(rng.random((len(ids), 256)) < 0.04, axis=1)
            fs = FeatureSet(ids, c, uv, codes[ids] ^ flips)
            (runner.submit_features if threaded else closer.add_keyframe_features)(stamp, fs)
        r = est.process_frame(stamp, ids, c, uv, is_keyframe=kf)
        if cfg.early_loops and len(r.keyframe_stamps_ns):  # as services/backend/loop/stage.py submits them
            (runner.submit_window if threaded else closer.note_window)(r.keyframe_stamps_ns, r.keyframe_T_WS)
        corr = runner.correction() if threaded else closer.correction()
        (runner.submit_status if threaded else closer.note_status)(stamp, r.status, corr @ r.T_WS)
        out.append((r.T_WS, corr @ r.T_WS, r.status))
    if threaded:
        assert runner.drain()
        runner.close()
    return times, gt, out, closer, est


def _loops_agree_with_ground_truth(closer, times, gt):
    stamp_to_gt = {int(round(t * 1e9)): T for t, T in zip(times, gt)}
    for old, new, T_rel, _ in closer.loops:
        Ta, Tb = stamp_to_gt[closer.node_stamps[old]], stamp_to_gt[closer.node_stamps[new]]
        err = inv_T(inv_T(Ta) @ Tb) @ T_rel
        assert np.linalg.norm(err[:3, 3]) < 0.1, (old, new, err[:3, 3])


@pytest.mark.e2e  # the estimator and the loop closer over 24-32 s simulated flights
def test_revisits_are_closed_and_every_loop_is_true():
    times, gt, out, closer, est = _run(32.0)
    c = closer.counts
    print(dict(c), "loops", len(closer.loops), "solve ms", np.round(closer.solve_ms, 1))
    assert c["accepted"] >= 1 and c["verified"] >= c["accepted"] and c["proposed"] >= c["verified"]
    _loops_agree_with_ground_truth(closer, times, gt)
    # the corrected trajectory is no worse than the odometry
    raw = np.array([np.linalg.norm(o[0][:3, 3] - T[:3, 3]) for o, T in zip(out, gt)])
    cor = np.array([np.linalg.norm(o[1][:3, 3] - T[:3, 3]) for o, T in zip(out, gt)])
    assert np.sqrt(np.mean(cor ** 2)) <= np.sqrt(np.mean(raw ** 2)) + 0.01
    # covisibility of the pose-graph nodes is recorded
    k = closer.graph.keys[len(closer.graph.keys) // 2]
    assert closer.covisibility.covisible(k, 5)


@pytest.mark.e2e  # the estimator and the loop closer over two 32 s simulated flights
def test_early_loops_correct_the_published_poses_sooner():
    """loop.early_loops: a verified loop joins the pose graph tied to the newest node by the window's relative pose,
    not window_keyframes later when its query keyframe leaves the window. The same loops are accepted and still
    true, the first correction reaches the published poses sooner, and the final BA's loops are the same pairs."""
    late = _run(32.0, cfg=LoopConfig(min_age_s=8.0, early_loops=False))
    early = _run(32.0, cfg=LoopConfig(min_age_s=8.0, early_loops=True))

    times, gt, out, closer, _ = early
    assert closer.counts["accepted_early"] >= 1
    assert closer.counts["accepted"] == late[3].counts["accepted"]
    assert [lp[:2] for lp in closer.loops] == [lp[:2] for lp in late[3].loops]
    _loops_agree_with_ground_truth(closer, times, gt)
    # one factor per loop: those whose query keyframe is still in the window at the end are in the graph already
    assert len(closer._early) >= 1
    assert len(closer.graph.loops) == len(late[3].graph.loops) + len(closer._early)
    # sensor time from a loop's query keyframe to its factor: the window's span (8 keyframes, 2.4 s here) less
    assert np.median(closer.loop_delays_s) <= np.median(late[3].loop_delays_s) - 1.0
    raw = np.array([np.linalg.norm(o[0][:3, 3] - T[:3, 3]) for o, T in zip(out, gt)])
    cor = np.array([np.linalg.norm(o[1][:3, 3] - T[:3, 3]) for o, T in zip(out, gt)])
    assert np.sqrt(np.mean(cor ** 2)) <= np.sqrt(np.mean(raw ** 2)) + 0.01


@pytest.mark.e2e  # the estimator and the loop closer over 24-32 s simulated flights
def test_relocalisation_after_blank_cameras():
    # 6 s without images (the 8-keyframe window forgets every landmark) with an accelerometer bias the
    # estimator has not fully learnt yet: the IMU-only segment drifts
    times, gt, out, closer, est = _run(24.0, blank=(12.0, 18.0), threaded=True, acc_bias=(0.15, -0.1, 0.05))
    c = closer.counts
    print(dict(c))
    assert c["losses"] >= 1 and c["relocalised"] >= 1
    _loops_agree_with_ground_truth(closer, times, gt)
    # the last second: relocalisation runs in the closer's own thread, so when its correction reaches the
    # published poses depends on the machine's load; judge the correction the closer holds at the end (after
    # draining), applied to the odometry of the last second, and print what was published
    after = times >= 23.0
    C = closer.correction()
    raw = np.array([np.linalg.norm(o[0][:3, 3] - T[:3, 3]) for o, T in zip(out, gt)])[after]
    pub = np.array([np.linalg.norm(o[1][:3, 3] - T[:3, 3]) for o, T in zip(out, gt)])[after]
    cor = np.array([np.linalg.norm((C @ o[0])[:3, 3] - T[:3, 3]) for o, T in zip(out, gt)])[after]
    print(f"after the gap: odometry error {raw.mean():.3f} m, relocalised {cor.mean():.3f} m (as published {pub.mean():.3f} m)")
    assert cor.mean() < 0.5 * raw.mean(), (raw.mean(), cor.mean())


@pytest.mark.e2e  # the estimator and the loop closer over 24-32 s simulated flights
def test_synchronous_runner_publishes_what_the_closer_computes_at_once():
    # loop.synchronous: no thread; each event is handled as it is submitted, so the published poses are exactly
    # those of calling the closer directly (the threaded runner publishes them whenever its thread gets there)
    times, gt, direct, closer_d, _ = _run(24.0, blank=(12.0, 18.0), acc_bias=(0.15, -0.1, 0.05))
    times, gt, sync, closer_s, _ = _run(24.0, blank=(12.0, 18.0), threaded="sync", acc_bias=(0.15, -0.1, 0.05))
    assert closer_s.counts["relocalised"] >= 1 and dict(closer_s.counts) == dict(closer_d.counts)
    moved = [not np.allclose(o[0], o[1]) for o in sync]
    assert any(moved)  # the correction reached the published poses
    for (raw_d, pub_d, st_d), (raw_s, pub_s, st_s) in zip(direct, sync):
        assert st_d == st_s
        np.testing.assert_array_equal(raw_d, raw_s)
        np.testing.assert_array_equal(pub_d, pub_s)


def test_synchronous_runner_has_no_thread_and_survives_a_bad_event():
    runner = ThreadedLoopCloser(LoopCloser(LoopConfig(), []), synchronous=True)
    assert runner._thread is None and runner.drain(0.0)
    runner.submit_record(object())  # not a keyframe record: counted and logged, the caller goes on
    assert runner.errors == 1 and runner.busy_s > 0  # its time is accounted for (eval ablation subtracts it)
    runner.close()


@pytest.mark.e2e  # the estimator and the loop closer over two simulated flights
def test_a_second_session_localises_in_the_first_ones_saved_map():
    """Session one maps the flight's first 14 s and saves its map; session two starts at 8 s in a frame of its own
    (yawed by 1.2 rad and shifted by metres) with that map loaded: once two matches agree it publishes in the map's
    frame (the ground truth's here), and its saved map is the first one extended."""
    times, gt, out, closer, est = _run(14.0)
    saved = closer.sparse_map({"source": "sim"})
    assert saved is not None and len(saved) > 10 and closer.aligned
    T_off = np.eye(4)
    T_off[:3, :3], T_off[:3, 3] = so3_exp([0.0, 0.0, 1.2]), [3.0, -2.0, 0.5]
    times, gt, out, closer2, est2 = _run(16.0, prior=saved, T_off=T_off, t_start=8.0)  # same landmark codes
    assert closer2.aligned and closer2.counts["map_relocalised"] == 1, dict(closer2.counts)
    t_align = (closer2.aligned_at_ns - times[0] * 1e9) * 1e-9
    assert t_align < 4.0, t_align
    after = [i for i, t in enumerate(times) if t * 1e9 > closer2.aligned_at_ns + 1e9]
    err = [np.linalg.norm(out[i][1][:3, 3] - gt[i][:3, 3]) for i in after]
    raw = [np.linalg.norm(out[i][0][:3, 3] - gt[i][:3, 3]) for i in after]
    assert len(err) > 20 and max(err) < 0.15 and min(raw) > 1.0, (max(err), min(raw))
    extended = closer2.sparse_map({"source": "sim 2"})
    assert len(extended) > len(saved) and len(extended.meta["sessions"]) == 2
    assert np.array_equal(extended.T_WS[:len(saved)], saved.T_WS)  # the saved map did not move
    assert int(np.sum(extended.edge_kind == 1)) >= 2  # the matches tie the sessions


def _stored_closer(n_neighbours):
    """A closer holding five marginalised keyframes (states 10..50) that see overlapping landmark ranges; a third
    of each one's features have no landmark position."""
    cams = sim.rig(2)
    closer = LoopCloser(LoopConfig(verify_neighbours=n_neighbours, min_inliers=5),
                        [VioCamera(c.T_SC, c.undistort, c.K[0, 0]) for c in cams])
    rng = np.random.default_rng(0)
    for k in range(1, 6):
        ids = np.arange(10 * k, 10 * k + 15, dtype=np.int64)  # 5 shared with the next keyframe
        fs = FeatureSet(ids, np.zeros(15, np.int16), rng.uniform(0, 500, (15, 2)),
                        rng.integers(0, 256, (15, 32), dtype=np.uint8))
        stamp = k * 10**9
        closer.add_keyframe_features(stamp, fs)
        known = {int(i): np.array([i, 2.0 * k, 1.0]) for i in ids if i % 3}  # landmark 3j: no position
        closer.add_record(KeyframeRecord(10 * k, stamp, np.eye(4), np.zeros(3), None, {int(i): [] for i in ids}, known))
    return closer


def test_verification_set_joins_the_neighbours_landmarks_once_each():
    own_fs, own_p = _stored_closer(0).verification_set(30)
    assert set(own_fs.landmark_ids) == {i for i in range(30, 45) if i % 3}
    fs, p = _stored_closer(1).verification_set(30)
    assert set(fs.landmark_ids) == {i for i in range(20, 55) if i % 3}  # states 20, 30 and 40
    assert len(fs.landmark_ids) == len(set(fs.landmark_ids)) == len(p) == len(fs.uv) == len(fs.descriptors)
    n_own = len(own_fs.landmark_ids)  # the candidate's own come first, unchanged
    np.testing.assert_array_equal(fs.landmark_ids[:n_own], own_fs.landmark_ids)
    np.testing.assert_array_equal(fs.descriptors[:n_own], own_fs.descriptors)
    np.testing.assert_array_equal(p[:n_own], own_p)
    # a shared landmark keeps the candidate's observation; one seen only by a neighbour keeps the neighbour's
    assert np.all(np.isfinite(p)) and p[list(fs.landmark_ids).index(44), 1] == 6.0
    assert p[list(fs.landmark_ids).index(22), 1] == 4.0
    assert set(_stored_closer(1).verification_set(50)[0].landmark_ids) == {i for i in range(40, 65) if i % 3}


def test_a_saved_map_ends_with_the_window_keyframes_moved_by_the_correction():
    """A checkpoint holds the keyframes still in the estimator's window, not only the pose-graph nodes: at their
    window pose moved by the newest node's correction, with features and landmark positions where enough are
    known, each linked to the one before it."""
    closer = _stored_closer(0)  # nodes 10..50 at the identity pose
    T_fix = np.eye(4)
    T_fix[:3, :3], T_fix[:3, 3] = so3_exp([0.0, 0.0, 0.3]), [1.0, -2.0, 0.5]
    closer.graph.estimate[50] = T_fix @ closer.graph.odom[50]  # as a solve that moved the newest node would
    rng = np.random.default_rng(1)
    window = []
    for k, n_known in ((6, 15), (7, 2)):  # keyframe 70 knows too few of its landmarks to verify against
        ids = np.arange(10 * k, 10 * k + 15, dtype=np.int64)
        stamp = k * 10**9
        closer.add_keyframe_features(stamp, FeatureSet(ids, np.zeros(15, np.int16), rng.uniform(0, 500, (15, 2)),
                                                       rng.integers(0, 256, (15, 32), dtype=np.uint8)))
        T_WS = _pose(0.1 * k, [0.5 * k, 0.0, 0.0])
        known = {int(i): np.array([float(i), 1.0, 3.0]) for i in ids[:n_known]}
        window.append(KeyframeRecord(10 * k, stamp, T_WS, np.zeros(3), None, {int(i): [] for i in ids}, known))
    m = closer.sparse_map({"source": "test"}, window + [closer._old[50][2]])  # a record already a node: once
    assert list(m.keys) == [10, 20, 30, 40, 50, 60, 70]
    assert list(m.stamps_ns[-2:]) == [6 * 10**9, 7 * 10**9]
    T_corr = closer.graph.correction()
    np.testing.assert_allclose(T_corr, T_fix, atol=1e-12)
    np.testing.assert_allclose(m.T_WS[5], T_fix @ window[0].T_WS, atol=1e-12)
    fs, p = m.features(5)
    np.testing.assert_array_equal(fs.landmark_ids, np.arange(60, 75))
    np.testing.assert_allclose(p[0], T_fix[:3, :3] @ [60.0, 1.0, 3.0] + T_fix[:3, 3], atol=1e-12)
    assert len(m.features(6)[0].landmark_ids) == 0  # posed, but nothing to verify a match against
    edges = {(int(a), int(b)): T for (a, b), T in zip(m.edges, m.edge_T)}
    np.testing.assert_allclose(edges[(50, 60)], inv_T(T_fix) @ T_fix @ window[0].T_WS, atol=1e-12)
    np.testing.assert_allclose(edges[(60, 70)], inv_T(window[0].T_WS) @ window[1].T_WS, atol=1e-12)


def _pose(yaw, t):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = so3_exp([0.0, 0.0, yaw]), t
    return T
