"""The frontend's keyframe descriptors as KeyframeFeatures (type 70) through the codec, and the run's final
trajectory outputs (FinalTrajectory, type 71), on frames of the frontend test room."""

import numpy as np

import frontend_scene as fs
from services.frontend.config import FrontendConfig
from services.frontend.tracker import MultiCameraTracker
from services.frontend.keyframe_features import keyframe_features_message
from services.app.run_outputs import loop_summary, write_final
from shared.codec import decode, encode
from shared.euroc import read_tum
from shared.messages import FinalTrajectory, Header


def test_keyframe_features_message_matches_the_tracker():
    room, cams = fs.BoxRoom(), fs.rig()
    tr = MultiCameraTracker(FrontendConfig(), cams)
    sent = 0
    prev = None
    for k in range(8):
        T = fs.body_pose(0.05 * k)
        out = tr.process(int(1e9 + 5e7 * k), [fs.render(room, c, T) for c in cams],
                         None if prev is None else fs.relative_rotation(prev, T))
        prev = T
        msg = keyframe_features_message(tr, out.stamp_ns, k)
        if not out.is_keyframe:
            assert msg is None
            continue
        assert msg is not None
        sent += 1
        back = decode(encode(msg))
        kd = tr.keyframe_descriptors[-1]
        assert back.keyframe_id == out.keyframe_id and back.header.stamp_ns == out.stamp_ns
        assert np.array_equal(back.descriptors, kd.descriptors) and np.array_equal(back.landmark_ids, kd.landmark_ids)
        assert np.isin(back.landmark_ids, out.landmark_ids).all() and len(back.landmark_ids) > 50
    assert sent >= 1


def test_final_trajectory_files(tmp_path):
    T = np.tile(np.eye(4), (5, 1, 1))
    T[:, :3, 3] = np.arange(15).reshape(5, 3)
    msg = FinalTrajectory(header=Header(stamp_ns=9), stamps_ns=np.arange(5, dtype=np.int64) * 10**8, T_WS=T,
                          keyframes=2, loops_proposed=3, loops_verified=1, loops_accepted=1, relocalisations=0)
    back = decode(encode(msg))
    traj = write_final(tmp_path, back)
    tum = read_tum(tmp_path / "trajectory_final.txt")
    assert np.allclose(tum.p_WS, T[:, :3, 3]) and np.array_equal(tum.stamps_ns, traj.stamps_ns)
    assert (tmp_path / "trajectory_final.csv").is_file() and (tmp_path / "trajectory.txt").is_file()
    assert loop_summary(back) == {"keyframes": 2, "proposed": 3, "verified": 1, "accepted": 1, "relocalisations": 0}
