"""The estimator (no transport) under bad IMU input: a gap, duplicated, backwards and NaN samples, and a frame
whose IMU never came. Frames inside a gap are refused (ImuDataError: the service drops and counts them); once
IMU resumes, the gap is bridged and it keeps tracking with a bounded error."""

import numpy as np
import pytest

import vio_sim as sim
from services.backend.config import BackendConfig
from services.backend.window.estimator import WindowedVioEstimator
from shared.vio.cameras import VioCamera
from shared.vio.imu_factors import ImuDataError


def _estimator(cams):
    return WindowedVioEstimator(BackendConfig(), [VioCamera(c.T_SC, c.undistort, c.K[0, 0]) for c in cams])


def test_imu_gap_duplicates_backwards_and_nan_samples():
    rng = np.random.default_rng(3)
    tr, cams, pts = sim.Trajectory(), sim.rig(2), sim.landmarks_cylinder(300, seed=2)
    est = _estimator(cams)
    st, om, ac = sim.imu(tr, 0.0, 5.1, 200.0, rng, gyro_nd=1.7e-4, acc_nd=2e-3)
    gap = (st > 2.0e9) & (st < 2.3e9)  # 300 ms without IMU
    t0 = 0.5
    T0 = tr.T_WS(np.array([t0]))[0]
    est.initialise(int(t0 * 1e9), T0[:3, :3], tr.velocity(np.array([t0]))[0], np.zeros(3), np.zeros(3),
                   static=True, p_W=T0[:3, 3])
    times = np.arange(t0, 5.0, 0.1)
    errs, statuses, j = [], [], 0
    refused = 0
    frames_refused = []
    for i, t in enumerate(times):
        stamp = int(round(t * 1e9))
        while j < len(st) and st[j] <= stamp:
            if not gap[j]:
                est.add_imu(int(st[j]), om[j], ac[j])
                if j % 50 == 0:  # a duplicate, a backwards sample and a NaN sample now and then
                    est.add_imu(int(st[j]), om[j], ac[j])
                    est.add_imu(int(st[j]) - 10_000_000, om[j], ac[j])
                    est.add_imu(int(st[j]) + 1, np.full(3, np.nan), ac[j])
                    refused += 3
            j += 1
        ids, c, uv = sim.observe(tr.T_WS(np.array([t]))[0], pts, cams, 0.5, rng, 25)
        try:
            r = est.process_frame(stamp, ids, c, uv, is_keyframe=(i % 2 == 0))
        except ImuDataError:  # inside the gap: the service drops the frame and counts it
            frames_refused.append(t)
            continue
        statuses.append(r.status)
        errs.append(np.linalg.norm(r.T_WS[:3, 3] - tr.T_WS(np.array([t]))[0][:3, 3]))
    assert est.imu.dropped == refused
    assert np.allclose(frames_refused, [2.1, 2.2]), frames_refused  # no IMU up to them yet; later frames bridge the gap
    assert all(s == "tracking" for s in statuses[-10:]), statuses
    assert max(errs) < 0.1, max(errs)  # the gap is bridged (vision holds the pose), no divergence


def test_frame_without_imu_coverage_is_refused_not_fatal():
    cams = sim.rig(2)
    est = _estimator(cams)
    est.initialise(0, np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3), static=True)
    for k in range(3):
        est.add_imu(k * 5_000_000, np.zeros(3), np.array([0, 0, 9.81]))
    with pytest.raises(ImuDataError, match="do not cover"):
        est.process_frame(2_000_000_000, np.zeros(0, np.int64), np.zeros(0, np.int16), np.zeros((0, 2)))
    # IMU arrives late, the next frame goes through
    for k in range(3, 500):
        est.add_imu(k * 5_000_000, np.zeros(3), np.array([0, 0, 9.81]))
    r = est.process_frame(2_100_000_000, np.zeros(0, np.int64), np.zeros(0, np.int16), np.zeros((0, 2)))
    assert r is not None and np.isfinite(r.T_WS).all()


# ----------------------------------------------------------------------------- the mapping's loop, no transport

_K_SMALL = np.array([[200.0, 0, 80], [0, 200.0, 60], [0, 0, 1]])
_DEPTH_2M = np.full((120, 160), 2.0, np.float32)


def _state(t: int, status: str = "tracking", x: float = 0.0):
    """An estimator state at stamp ``t`` with the body at (x, 0, 0)."""
    from shared.codec import Header
    from shared.messages import EstimatorState

    T = np.eye(4)
    T[0, 3] = x
    return EstimatorState(header=Header(stamp_ns=t), T_WS=T, v_W=np.zeros(3), gyro_bias=np.zeros(3),
                          acc_bias=np.zeros(3), covariance=np.full((15, 15), np.nan), status=status)


def _depth_frame(t: int):
    """A small depth frame at stamp ``t``: a wall 2 m ahead, 5 cm sigma."""
    from shared.codec import Header
    from shared.messages import DepthFrame

    return DepthFrame(header=Header(stamp_ns=t), depth=_DEPTH_2M, sigma=np.full_like(_DEPTH_2M, 0.05), K=_K_SMALL,
                      T_WC=np.eye(4), T_SC=np.eye(4), source="stereo")


def test_mapping_freezes_its_submaps_when_the_back_end_resets():
    """After a 'reset' state the old submaps stop following keyframes (the new back end's ids mean other
    keyframes, in another world frame) and the next depth frame starts a new submap."""
    from services.mapping.config import MappingConfig
    from services.mapping.node import make_node
    from shared.codec import Header
    from shared.messages import Keyframes

    loop = make_node(MappingConfig())
    state, frame = _state, _depth_frame
    for t in (1, 2, 3):
        loop.on_state(state(t))
        loop.on_depth(frame(t))
    loop.integrate_waiting()
    loop.on_keyframes(Keyframes(header=Header(stamp_ns=3), ids=np.array([0]), stamps_ns=np.array([1]),
                                T_WS=np.eye(4)[None]))
    assert len(loop.mapper.submaps) == 1 and loop.mapper.submaps[0].keyframe_id == 0
    loop.on_state(state(10, "reset"))
    loop.on_state(state(11, x=5.0))  # the new back end's world frame
    loop.on_depth(frame(11))
    loop.integrate_waiting()
    assert len(loop.mapper.submaps) == 2 and loop.counts["estimator_resets"] == 1
    old, new = loop.mapper.submaps
    assert new.n_frames == 1 and np.allclose(new.T_WM[0, 3], 5.0)
    # keyframe 0 of the new back end must not move the old submap
    T = np.eye(4)
    T[1, 3] = 3.0
    moved = loop.mapper.update_keyframes(np.array([0]), np.array([11]), T[None])
    assert old.id not in moved and np.allclose(old.T_WM, np.eye(4))


def test_mapping_skips_frames_the_estimator_had_no_pose_for_and_waits_for_the_others():
    """A depth frame at the stamp of an 'initialising' state is skipped at once and counted apart (it can never get a
    pose); a frame whose state is merely late waits for it and is integrated when it comes."""
    from services.mapping.config import MappingConfig
    from services.mapping.node import make_node

    loop = make_node(MappingConfig(pose_wait_s=60.0))
    state, frame = _state, _depth_frame
    loop.on_state(state(1, "initialising"))
    loop.on_depth(frame(1))
    loop.on_depth(frame(2))  # its state has not come yet
    loop.integrate_waiting()
    assert loop.counts["skipped_no_estimate"] == 1 and loop.counts["integrated"] == 0
    assert len(loop.waiting) == 1 and loop.counts["dropped_no_pose"] == 0
    loop.on_state(state(2, "tracking"))
    loop.integrate_waiting()
    assert loop.counts["integrated"] == 1 and not loop.waiting and loop.counts["skipped_no_estimate"] == 1


def test_mapping_checkpoints_in_a_thread_and_skips_one_that_falls_due_while_writing(tmp_path, monkeypatch):
    """The checkpoint snapshots the map in the loop and writes it in a thread: the loop goes on integrating while the
    file is written; a checkpoint due meanwhile is skipped (counted); the final write waits for the thread."""
    import threading

    from services.mapping import node as mapping_node
    from services.mapping import store as mapping_store
    from services.mapping.config import MappingConfig
    from services.mapping.io import load_map

    release, real_write = threading.Event(), mapping_store.write_map_arrays
    monkeypatch.setattr(mapping_store, "write_map_arrays",
                        lambda arrays, path: (release.wait(10.0), real_write(arrays, path))[1])
    now = [0.0]
    nd = mapping_node.make_node(MappingConfig(checkpoint_period_s=1.0, mesh_period_s=100.0), str(tmp_path),
                                clock=lambda: now[0])

    def frame(t):
        nd.on_state(_state(t, x=0.01 * t))
        return nd.on_depth(_depth_frame(t))

    frame(1)
    now[0] = 1.5
    frame(2)  # the checkpoint falls due: snapshot of 2 frames, the writer waits for `release`
    assert nd.store.writing
    now[0] = 3.0
    frame(3)  # integrated while the first checkpoint is being written; the second is skipped
    assert nd.counts["integrated"] == 3 and nd.counts["checkpoints_skipped_busy"] == 1
    release.set()
    nd.store.wait()
    saved = load_map(tmp_path / "map" / "dense.npz")
    assert sum(sm.n_frames for sm in saved.submaps) == 2  # the snapshot, not the map as it was when written
    nd.close()  # the final map: all three frames
    assert sum(sm.n_frames for sm in load_map(tmp_path / "map" / "dense.npz").submaps) == 3


def test_map_snapshots_copy_only_the_submaps_that_changed(tmp_path):
    """map_arrays with a reuse dict gives a closed, unchanged submap's fields from the last snapshot (the same
    arrays) and copies the current one again; the snapshot loads back as the map it was taken of."""
    from services.mapping.config import MappingConfig
    from services.mapping.io import map_arrays, write_map_arrays, load_map
    from services.mapping.node import make_node

    loop = make_node(MappingConfig())
    K, depth = _K_SMALL, _DEPTH_2M
    sigma = np.full_like(depth, 0.05)
    loop.mapper.integrate(depth, sigma, K, np.eye(4), np.eye(4), 1)
    loop.mapper.estimator_reset()  # freezes submap 0; the next frame starts submap 1
    loop.mapper.integrate(depth, sigma, K, np.eye(4), np.eye(4), 2)
    reuse: dict = {}
    first = map_arrays(loop.mapper, reuse)
    loop.mapper.integrate(depth, sigma, K, np.eye(4), np.eye(4), 3)  # submap 1 grows
    second = map_arrays(loop.mapper, reuse)
    assert second["s0/Lv"] is first["s0/Lv"] and second["s1/wv"] is not first["s1/wv"]
    assert not np.array_equal(second["s1/wv"], first["s1/wv"])  # the third frame is in the new copy
    for key, arr in map_arrays(loop.mapper).items():  # the same content as a snapshot taken afresh
        assert np.array_equal(second[key], arr), key
    back = load_map(write_map_arrays(second, tmp_path / "dense.npz"))
    assert [sm.n_frames for sm in back.submaps] == [1, 2]
