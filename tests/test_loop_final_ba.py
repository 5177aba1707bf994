"""Final bundle adjustment over all keyframes (with IMU) on simulated VIO data: it improves the ATE of the
causal trajectory; the keyframe history (the estimator's marginalisation listener) is complete."""

import dataclasses

import numpy as np

import vio_sim as sim
from services.backend.config import BackendConfig
from services.backend.window.estimator import WindowedVioEstimator
from shared.vio.cameras import VioCamera
from services.backend.loop.config import LoopConfig
from services.backend.loop.final_ba import bundle_adjust, follow_keyframes
from services.backend.loop.history import KeyframeHistory
from services.backend.loop.stage import LoopClosure
from shared.map_folder import UNALIGNED_FRAME
from shared.geometry import inv_T, make_T, so3_exp, so3_log
from shared.metrics.ate import compute_ate

IMU_NOISE = dict(gyro_nd=1.7e-4, acc_nd=2e-3, gyro_rw=1.9e-5, acc_rw=3e-3)


def _run(t_end=24.0, t0=0.5, rate=10.0, seed=3, sigma_px=1.0):
    rng = np.random.default_rng(seed)
    tr = sim.Trajectory()
    pts = sim.landmarks_cylinder(400, seed=4)
    cams = sim.rig(2)
    hist = KeyframeHistory()
    est = WindowedVioEstimator(BackendConfig(compute_covariance=False),
                               [VioCamera(c.T_SC, c.undistort, c.K[0, 0]) for c in cams], on_marginalise=[hist])
    st, om, ac = sim.imu(tr, 0.0, t_end + 0.1, 200.0, rng, gyro_bias=(0.002, -0.001, 0.003),
                         acc_bias=(0.05, -0.03, 0.02), **IMU_NOISE)
    T0 = tr.T_WS(np.array([t0]))[0]
    est.initialise(int(round(t0 * 1e9)), T0[:3, :3], tr.velocity(np.array([t0]))[0], np.zeros(3), np.zeros(3),
                   static=True, p_W=T0[:3, 3])
    times = np.arange(t0, t_end, 1.0 / rate)
    gt = tr.T_WS(times)
    stamps, T_causal, j = [], [], 0
    for i, (t, T) in enumerate(zip(times, gt)):
        stamp = int(round(t * 1e9))
        while j < len(st) and st[j] <= stamp:
            est.add_imu(st[j], om[j], ac[j])
            j += 1
        ids, c, uv = sim.observe(T, pts, cams, sigma_px, rng, 25)
        r = est.process_frame(stamp, ids, c, uv, is_keyframe=(i % 3 == 0))
        stamps.append(stamp)
        T_causal.append(r.T_WS)
    return np.array(stamps), np.array(T_causal), gt, est, hist


def test_final_ba_improves_on_the_causal_trajectory():
    stamps, T_causal, gt, est, hist = _run()
    # every keyframe that left the window was captured, with finite relative covariances from the marginals
    # (a rare failed marginal computation in the window falls back to a loose covariance, counted)
    assert len(hist.records) > 50 and hist.fallback_covariances <= 0.05 * len(hist.records)
    assert all(np.all(np.isfinite(r.rel_cov_to_next)) and np.all(np.linalg.eigvalsh(r.rel_cov_to_next) > 0)
               for r in hist.records)
    assert all(r.imu_to_next is not None and r.next_state is not None for r in hist.records)
    records = hist.records + hist.capture_window(est)
    assert [r.state for r in records] == sorted({r.state for r in records})
    res = bundle_adjust(records, est.cameras, est.cfg.sigma_px, est.cfg.cauchy_k)
    assert res.final_error < res.initial_error
    T_final = follow_keyframes(stamps, T_causal, res.stamps_ns, res.T_WS)
    ate_causal = compute_ate(stamps, gt[:, :3, 3], stamps, T_causal[:, :3, 3]).rmse_m
    ate_final = compute_ate(stamps, gt[:, :3, 3], stamps, T_final[:, :3, 3]).rmse_m
    print(f"ATE causal {ate_causal:.4f} m, final BA {ate_final:.4f} m, {res.landmarks} landmarks, "
          f"{res.observations} observations, {len(res.stamps_ns)} keyframes")
    assert ate_final < 0.8 * ate_causal, (ate_causal, ate_final)


def test_follow_keyframes_blends_the_correction_between_keyframes():
    rng = np.random.default_rng(0)
    T = np.array([make_T(so3_exp(rng.normal(scale=0.5, size=3)), rng.normal(size=3)) for _ in range(6)])
    stamps = np.arange(6, dtype=np.int64) * 100
    C = make_T(so3_exp(np.array([0.0, 0.0, 0.3])), np.array([1.0, 0.0, 0.0]))  # the final BA's correction at 300
    out = follow_keyframes(stamps, T, np.array([0, 300]), np.array([T[0], C @ T[3]]))
    assert np.allclose(out[0], T[0]) and np.allclose(out[3], C @ T[3])
    for i in (1, 2):  # a third and two thirds of the way from no correction to C
        step = make_T(so3_exp(np.array([0.0, 0.0, 0.3 * i / 3])), np.array([i / 3, 0.0, 0.0]))
        assert np.allclose(out[i], step @ T[i])
    assert np.allclose(out[4:], C @ T[4:])  # after the last keyframe: rigidly with it
    # the frames after a keyframe were solved against another pose of it than its own published one (the window's
    # solve, not the fast path's prediction): they move with that anchor, the frames before it with its own pose
    anchor = make_T(np.eye(3), T[3, :3, 3] + [0.0, 0.0, 0.05])
    out = follow_keyframes(stamps, T, np.array([0, 300]), np.array([T[0], C @ T[3]]), np.array([T[0], anchor]))
    assert np.allclose(out[3], C @ T[3]) and np.allclose(out[2], make_T(so3_exp(np.array([0.0, 0.0, 0.2])),
                                                                        np.array([2 / 3, 0.0, 0.0])) @ T[2])
    assert np.allclose(out[4:], C @ T[3] @ inv_T(anchor) @ T[4:])
    # a keyframe with no frame of its own (the back end's first, published as 'initialising') but an anchor: the
    # frames after it blend from its correction, not only the next keyframe's
    shift = make_T(np.eye(3), np.array([0.0, 0.1, 0.0]))
    out = follow_keyframes(stamps[1:], T[1:], np.array([0, 300]), np.array([shift @ T[0], C @ T[3]]),
                           np.array([T[0], np.full((4, 4), np.nan)]))
    D = inv_T(shift) @ C
    step = make_T(so3_exp(so3_log(D[:3, :3]) / 3), D[:3, 3] / 3)
    assert np.allclose(out[0], shift @ step @ T[1]) and np.allclose(out[2], C @ T[3])


def test_frames_before_a_relocalisation_follow_their_own_frame_when_the_window_solved_their_keyframe_after_it():
    """A run localising in a saved map publishes its first frames in its own frame 'odom', later ones in the map's.
    The window may take a keyframe published in 'odom' after the relocalisation: its anchor is then in the map's
    frame, and the frames after that keyframe (still in 'odom') must not be moved by it (they were 2.5 m off in a
    live V2_01 run in a V1_02 map)."""
    truth = np.array([make_T(so3_exp(np.array([0.0, 0.0, 0.05 * i])), np.array([0.1 * i, 0.0, 1.0]))
                      for i in range(20)])
    T_map_odom = make_T(so3_exp(np.array([0.0, 0.0, 0.7])), np.array([2.0, -1.0, 0.3]))
    stamps = np.arange(20, dtype=np.int64) * 50_000_000
    odom = np.arange(20) < 10  # relocalised between frames 9 and 10
    published = np.where(odom[:, None, None], inv_T(T_map_odom) @ truth, truth)
    loop = LoopClosure(LoopConfig(), None, None, None, None)
    loop._frame_ids = [UNALIGNED_FRAME if o else "W" for o in odom]
    kf = np.array([0, 5, 10, 15])
    for i in kf:  # keyframe 5 was taken by the window after the relocalisation: its anchor is in the map's frame
        frame = UNALIGNED_FRAME if i < 5 else "W"
        anchor = published[i] if frame == UNALIGNED_FRAME else truth[i]
        loop._kf_anchor[int(stamps[i])] = (anchor, frame)
    out = loop._follow(stamps, published, stamps[kf], truth[kf])  # the final BA put every keyframe in the map's frame
    assert np.abs(out[:, :3, 3] - truth[:, :3, 3]).max() < 1e-9
    assert np.abs(out[:, :3, :3] - truth[:, :3, :3]).max() < 1e-9


def test_loop_observations_merge_a_new_track_into_the_old_landmark():
    """Cut every track in two halfway (a new landmark id from the middle keyframe on, as when a place is seen
    again): the loop observations that pair each new id with its old one put back the uncut problem."""
    stamps, T_causal, gt, est, hist = _run(t_end=10.0)
    records = hist.records + hist.capture_window(est)
    whole = bundle_adjust(records, est.cameras, est.cfg.sigma_px, est.cfg.cauchy_k)
    mid, NEW = len(records) // 2, 10**6
    cut = records[:mid] + [dataclasses.replace(r, obs={lm + NEW: o for lm, o in r.obs.items()},
                                               landmarks={lm + NEW: p for lm, p in r.landmarks.items()})
                           for r in records[mid:]]
    both = sorted(set().union(*(r.obs for r in records[:mid])) & set().union(*(r.obs for r in records[mid:])))
    first = {lm: next(r for r in records[mid:] if lm in r.obs) for lm in both}  # the new track's first keyframe
    pairs = [(first[lm].state, *first[lm].obs[lm][0], lm, lm + NEW) for lm in both]
    q = records[mid]
    apart = bundle_adjust(cut, est.cameras, est.cfg.sigma_px, est.cfg.cauchy_k)
    joined = bundle_adjust(cut, est.cameras, est.cfg.sigma_px, est.cfg.cauchy_k, loop_observations=pairs)
    assert len(pairs) > 10 and joined.merged == len(pairs) and apart.merged == 0
    assert (joined.observations, joined.landmarks) == (whole.observations, whole.landmarks)
    assert apart.landmarks > whole.landmarks and apart.observations < whole.observations
    assert np.abs(joined.T_WS[:, :3, 3] - whole.T_WS[:, :3, 3]).max() < 1e-3
    # two landmarks one keyframe sees side by side are two points: such a pair is left apart
    a, b = list(q.obs)[:2]
    kept = bundle_adjust(records, est.cameras, est.cfg.sigma_px, est.cfg.cauchy_k,
                         loop_observations=[(q.state, *q.obs[a][0], a, b)])
    assert kept.merged == 0 and kept.observations == whole.observations


def test_a_second_solve_without_sliding_tracks_undoes_their_pull():
    """Tracks that slide (a feature on a silhouette, a drifting KLT track) are not points: each keyframe sees them a
    little further along, and the one-solve BA bends the poses to fit them. Landmarks whose RMS reprojection error
    is far above the median one's are dropped before a second solve, which lands near the BA of the clean tracks."""
    stamps, T_causal, gt, est, hist = _run(t_end=14.0)
    records = hist.records + hist.capture_window(est)
    focal = est.cameras[0].focal_px
    lms = sorted({lm for r in records for lm in r.obs})
    sliding = set(lms[::5])  # a fifth of the landmarks slide by 0.8 px per keyframe, all the same way
    first = {}
    for i, r in enumerate(records):
        for lm in r.obs:
            first.setdefault(lm, i)
    slid = [dataclasses.replace(r, obs={lm: [(c, xy + (0.8 * (i - first[lm]) / focal, 0.0) if lm in sliding else xy)
                                             for c, xy in o] for lm, o in r.obs.items()})
            for i, r in enumerate(records)]

    def ate(res):
        idx = np.searchsorted(stamps, res.stamps_ns)
        return compute_ate(res.stamps_ns, gt[idx, :3, 3], res.stamps_ns, res.T_WS[:, :3, 3]).rmse_m

    args = (est.cameras, est.cfg.sigma_px, est.cfg.cauchy_k)
    ratio = LoopConfig().final_ba_prune_ratio  # the default
    clean, once, twice = bundle_adjust(records, *args), bundle_adjust(slid, *args), bundle_adjust(slid, *args,
                                                                                                  prune_ratio=ratio)
    print(f"keyframe ATE: clean tracks {ate(clean):.4f} m, sliding one solve {ate(once):.4f} m, "
          f"two solves {ate(twice):.4f} m ({twice.pruned} of {twice.landmarks + twice.pruned} landmarks dropped)")
    assert once.pruned == 0 and twice.pruned > 0
    assert twice.landmarks + twice.pruned == once.landmarks
    assert ate(once) > 1.5 * ate(clean)  # the slide pulls the one-solve BA
    assert ate(twice) < 0.5 * (ate(once) + ate(clean))  # the second solve recovers most of it
    clean_twice = bundle_adjust(records, *args, prune_ratio=ratio)
    assert ate(clean_twice) < 1.2 * ate(clean)  # with clean tracks it costs little
