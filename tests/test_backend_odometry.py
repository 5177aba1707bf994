"""The per-frame fast path (services/frontend/odometry.py, fast_path.py): the same motion-only solve as the
window estimator's, from the windows the back end publishes; ground truth on a synthetic rig; stale and late input."""

import numpy as np
import pytest

import vio_sim as sim
from services.backend.config import BackendConfig
from services.backend.window.estimator import WindowedVioEstimator
from shared.vio.cameras import VioCamera
from services.frontend.odometry import FrameTracker, StaleFrame
from shared.codec import Header, decode, encode
from shared.messages import EstimatorWindow

GYRO_BIAS = np.array([0.002, -0.001, 0.003])
ACC_BIAS = np.array([0.05, -0.03, 0.02])


def _window(est: WindowedVioEstimator, res, T_corr=np.eye(4), status="tracking") -> EstimatorWindow:
    """What the back end publishes after a keyframe (WindowStage.window_message), through the codec."""
    ids, p_W = est.window_points()
    msg = EstimatorWindow(header=Header(stamp_ns=int(res.stamp_ns), seq=0, frame_id="W"), T_WS=res.T_WS,
                          v_W=res.v_W, gyro_bias=res.gyro_bias, acc_bias=res.acc_bias, T_corr=T_corr,
                          landmark_ids=ids, p_W=p_W, status=status)
    return decode(encode(msg))


def _sim(t_end=6.0, rate=10.0, t0=0.5, seed=1):
    rng = np.random.default_rng(seed)
    tr = sim.Trajectory()
    pts = sim.landmarks_cylinder(300, seed=2)
    cams = sim.rig(2)
    st, om, ac = sim.imu(tr, 0.0, t_end + 0.1, 200.0, rng, gyro_nd=1.7e-4, acc_nd=2e-3, gyro_rw=1.9e-5,
                         acc_rw=3e-3, gyro_bias=GYRO_BIAS, acc_bias=ACC_BIAS)
    times = np.arange(t0, t_end, 1.0 / rate)
    frames = [sim.observe(T, pts, cams, 0.5, rng, 25) for T in tr.T_WS(times)]
    T0 = tr.T_WS(np.array([t0]))[0]
    return tr, cams, (st, om, ac), times, frames, T0, tr.velocity(np.array([t0]))[0]


def test_fast_path_equals_the_estimators_own_motion_only_solve_and_tracks_ground_truth():
    tr, cams, (st, om, ac), times, frames, T0, v0 = _sim()
    bcams = [VioCamera(c.T_SC, c.undistort, c.K[0, 0]) for c in cams]
    cfg = BackendConfig(fast_path_settle_s=0.0)  # the anchor pinned from the first window, as the estimator pins it
    est = WindowedVioEstimator(cfg, bcams)
    est.initialise(int(round(times[0] * 1e9)), T0[:3, :3], v0, np.zeros(3), np.zeros(3), static=True, p_W=T0[:3, 3])
    fast = FrameTracker(cfg, bcams)
    j, diffs, errs = 0, [], []
    for i, (t, (ids, c, uv)) in enumerate(zip(times, frames)):
        stamp = int(round(t * 1e9))
        while j < len(st) and st[j] <= stamp:
            est.add_imu(st[j], om[j], ac[j])
            fast.add_imu(st[j], om[j], ac[j])
            j += 1
        is_kf = i % 3 == 0
        mine = fast.track(stamp, ids, c, uv)
        if est.wants_frame(stamp, is_kf):
            res = est.process_frame(stamp, ids, c, uv, is_keyframe=is_kf)
            fast.set_window(_window(est, res))
        else:  # the estimator's own non-keyframe path: the same solve against the same window
            res = est.process_frame(stamp, ids, c, uv, is_keyframe=False)
            diffs.append(np.abs(mine.T_WS - res.T_WS).max())
            assert mine.status == res.status and mine.solved
            assert i < 4 or mine.status == "tracking"  # once the window has triangulated landmarks
        if mine is not None:
            errs.append(np.linalg.norm(mine.T_WS[:3, 3] - tr.T_WS(np.array([t]))[0][:3, 3]))
    assert len(diffs) > 20 and max(diffs) < 1e-6, max(diffs)
    assert len(errs) == len(times) - 1  # every frame after the first window
    assert np.sqrt(np.mean(np.square(errs))) < 0.03  # 0.5 px noise, EuRoC-class IMU noise (observed ~1 cm)


def test_window_order_stale_frames_and_missing_imu():
    tr, cams, (st, om, ac), times, frames, T0, v0 = _sim(t_end=2.0)
    bcams = [VioCamera(c.T_SC, c.undistort, c.K[0, 0]) for c in cams]
    cfg = BackendConfig()
    fast = FrameTracker(cfg, bcams)
    stamp = int(round(times[3] * 1e9))
    assert fast.track(stamp, *frames[3]) is None  # no window yet
    est = WindowedVioEstimator(cfg, bcams)
    est.initialise(stamp, T0[:3, :3], v0, np.zeros(3), np.zeros(3), static=True, p_W=T0[:3, 3])
    for s, w, a in zip(st, om, ac):
        est.add_imu(s, w, a)
    res = est.process_frame(stamp, *frames[3])
    assert fast.set_window(_window(est, res))
    with pytest.raises(StaleFrame):
        fast.track(int(round(times[2] * 1e9)), *frames[2])
    from shared.vio.imu_factors import ImuDataError

    with pytest.raises(ImuDataError):  # the fast path has been given no IMU at all
        fast.track(int(round(times[4] * 1e9)), *frames[4])
    import dataclasses

    older = dataclasses.replace(_window(est, res), header=Header(stamp_ns=stamp - 10**8, seq=1, frame_id="W"))
    assert not fast.set_window(older)  # an older window never replaces a newer anchor ...
    fast.reset()  # ... unless the back end restarted (the node resets on a 'reset' window)
    assert fast.track(stamp, *frames[3]) is None
    assert fast.set_window(older)
    kf = fast.track(stamp - 10**8, *frames[3])  # the anchor's own stamp: the window's estimate itself
    assert np.allclose(kf.T_WS, res.T_WS)


def test_fast_path_applies_the_loop_correction_resets_and_waits_only_when_asked():
    import dataclasses

    from services.frontend.fast_path import FastPath
    from services.app.system_config import load_system_config
    from shared.messages import FeatureFrame, ImuSample
    from shared.rig import RigConfig, load_rig_config

    tr, cams, (st, om, ac), times, frames, T0, v0 = _sim(t_end=2.0)
    bcams = [VioCamera(c.T_SC, c.undistort, c.K[0, 0]) for c in cams]
    est = WindowedVioEstimator(BackendConfig(), bcams)
    s0 = int(round(times[0] * 1e9))
    est.initialise(s0, T0[:3, :3], v0, np.zeros(3), np.zeros(3), static=True, p_W=T0[:3, 3])
    for s, w, a in zip(st, om, ac):
        est.add_imu(s, w, a)
    res = est.process_frame(s0, *frames[0])
    T_corr = np.eye(4)
    T_corr[:3, 3] = [1.0, -2.0, 0.5]

    node = FastPath(load_system_config(None, []).backend, load_rig_config(RigConfig()))  # the bundled EuRoC rig ...
    node.tracker = FrameTracker(node.cfg, bcams)  # ... tracking on the synthetic rig the frames come from
    for s, w, a in zip(st, om, ac):
        node.on_imu(ImuSample(header=Header(stamp_ns=int(s), seq=0, frame_id="S"), omega_S=w, acc_S=a))

    def frame(i, kf=False, dt_ns=0):
        ids, c, uv = frames[i]
        return FeatureFrame(header=Header(stamp_ns=int(round(times[i] * 1e9)) + dt_ns, seq=i, frame_id="rig"),
                            landmark_ids=ids, camera_index=c.astype(np.int16), uv=uv.astype(np.float32),
                            p_W_init=np.full((len(ids), 3), np.nan), is_keyframe=kf)

    e = node.state_of(frame(0, kf=True))
    assert e.status == "initialising"  # before the first window
    node.on_window(_window(est, res, T_corr))
    e = node.state_of(frame(1))
    plain = node.tracker.track(int(round(times[1] * 1e9)), *frames[1])
    assert np.allclose(e.T_WS, T_corr @ plain.T_WS) and np.allclose(e.v_W, plain.v_W)
    assert np.isnan(e.covariance).all() and e.status == plain.status
    assert node.state_of(frame(0, dt_ns=-10**7)) is None and node.dropped == 1  # older than the anchor: dropped and counted
    reset = dataclasses.replace(_window(est, res), status="reset")
    node.on_window(reset)  # a restarted back end: the old window is forgotten
    statuses = [node.state_of(frame(k)).status for k in (3, 4)]
    assert statuses == ["reset", "initialising"]  # 'reset' once, then no pose until the new back end's window
    node.on_window(_window(est, res, T_corr))
    assert node.window_stamp() == -1  # live: never waits for a window
    node.waits_for_window = True
    node.state_of(frame(2, kf=True))
    assert node.window_stamp() == int(round(times[2] * 1e9))  # lockstep: that keyframe's window



def _drift_from_a_wrong_anchor(cfg: BackendConfig, dv: np.ndarray, earlier_window: bool = False) -> list[float]:
    """Position errors [m] of the frames the fast path tracks for 0.9 s from one window whose velocity is off by
    ``dv`` (as a window just initialised may be); ``earlier_window``: the tracker had a window 1 s before it."""
    import dataclasses

    tr, cams, (st, om, ac), times, frames, T0, v0 = _sim(t_end=3.0, rate=20.0)
    bcams = [VioCamera(c.T_SC, c.undistort, c.K[0, 0]) for c in cams]
    est = WindowedVioEstimator(BackendConfig(), bcams)
    est.initialise(int(round(times[0] * 1e9)), T0[:3, :3], v0, np.zeros(3), np.zeros(3), static=True,
                   p_W=T0[:3, 3])
    fast, j, errs = FrameTracker(cfg, bcams), 0, []
    k = 20  # the anchor: 1 s in, the window has triangulated its landmarks
    for i, (t, obs) in enumerate(zip(times, frames)):
        stamp = int(round(t * 1e9))
        while j < len(st) and st[j] <= stamp:
            est.add_imu(st[j], om[j], ac[j])
            fast.add_imu(st[j], om[j], ac[j])
            j += 1
        if i <= k:
            res = est.process_frame(stamp, *obs, is_keyframe=i % 4 == 0 or i == k)
            if i == k or (i == 0 and earlier_window):
                w = _window(est, res)
                fast.set_window(dataclasses.replace(w, v_W=np.asarray(w.v_W) + (dv if i == k else 0.0)))
        elif i <= k + 18:
            errs.append(np.linalg.norm(fast.track(stamp, *obs).T_WS[:3, 3] - tr.T_WS(np.array([t]))[0][:3, 3]))
    return errs


def test_while_the_window_is_young_the_fast_path_corrects_its_anchors_velocity_with_the_frames_landmarks():
    """Pinned, the anchor keyframe's velocity error becomes the frames' position error (the IMU factor over a
    fraction of a second is far tighter than the reprojections). Within backend.fast_path_settle_s of the first
    window the anchor's velocity and bias are held by priors instead, and the frames' landmarks correct them; later
    windows are pinned (the window's estimate beats one frame's)."""
    pinned, young = BackendConfig(fast_path_settle_s=0.0), BackendConfig(fast_path_settle_s=2.0)
    dv = np.array([0.08, -0.06, 0.0])  # 0.1 m/s: 9 cm after 0.9 s
    e_pinned, e_young = _drift_from_a_wrong_anchor(pinned, dv), _drift_from_a_wrong_anchor(young, dv)
    assert e_pinned[-1] > 0.06  # dead reckoning from the wrong velocity
    assert e_young[-1] < 0.5 * e_pinned[-1], (e_young, e_pinned)  # observed 0.3x
    # a window 1 s after the first, with fast_path_settle_s 0.5 s: pinned, as with the settling off
    late = BackendConfig(fast_path_settle_s=0.5)
    assert _drift_from_a_wrong_anchor(late, dv, earlier_window=True) == \
        _drift_from_a_wrong_anchor(pinned, dv, earlier_window=True)
