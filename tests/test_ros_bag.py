"""ROS bags without ROS: image encodings, stereo matching by header stamp, topic choice and its errors, Kalibr
calibrations against the same rig as EuRoC sensor.yaml, and real EuRoC frames written as ROS 2 (MCAP, sqlite3)
and ROS 1 bags converted back to the identical EuRoC folder, whose estimator trajectory equals the original's (to round-off)."""
import numpy as np
import pytest

from services.app.datasets.ros_bag import BagError, choose_topics, image_to_grey, is_ros_bag, match_stereo
from tests.helpers_data import require_real_data
from tests.ros_bags import image_msg, write_bag, write_kalibr


@pytest.fixture(scope="module")
def typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def _img():
    y, x = np.mgrid[0:24, 0:32]
    return (x * 6 + y * 3).astype(np.uint8)  # smooth, so a demosaiced Bayer image stays close


@pytest.mark.unit
@pytest.mark.parametrize("enc", ["mono8", "mono16", "bgr8", "rgb8", "png"])
def test_lossless_encodings_decode_to_the_same_grey(typestore, enc):
    img = _img()
    msg = image_msg(typestore, img, 5, "cam0", enc)
    got = image_to_grey(msg, msg.__msgtype__)
    assert got.dtype == np.uint8 and np.abs(got.astype(int) - img).max() <= (1 if enc in ("bgr8", "rgb8") else 0)


@pytest.mark.unit
def test_bayer_and_jpeg_are_close_and_unknown_encodings_are_named(typestore):
    img = _img()
    for enc, tol in (("bayer_rggb8", 3.0), ("jpeg", 3.0)):
        msg = image_msg(typestore, img, 5, "cam0", enc)
        got = image_to_grey(msg, msg.__msgtype__)
        assert np.abs(got[2:-2, 2:-2].astype(float) - img[2:-2, 2:-2]).mean() < tol
    msg = image_msg(typestore, img, 5, "cam0", "mono8")
    msg.encoding = "yuv422"
    with pytest.raises(BagError, match="yuv422"):
        image_to_grey(msg, msg.__msgtype__)


@pytest.mark.unit
def test_stereo_frames_match_within_the_tolerance_one_to_one():
    left = np.array([0, 50, 100, 150, 200]) * 1_000_000
    right = np.array([1, 49, 151, 152, 230]) * 1_000_000  # 100 missing, 150 has two candidates, 200 too far
    pairs, unmatched = match_stereo([left, right], 2_000_000)
    assert pairs.tolist() == [[0, 0], [1, 1], [3, 2]]
    assert unmatched == [2, 2]


@pytest.mark.unit
def test_topic_choice_and_its_errors():
    img, cimg, imu = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/Imu"
    topics = {"/cam1/image_raw": (img, 10), "/cam0/image_raw": (img, 10), "/cam0/image_raw/compressed": (cimg, 10),
              "/imu0": (imu, 200), "/tf": ("tf2_msgs/msg/TFMessage", 3)}
    assert choose_topics(topics) == (["/cam0/image_raw", "/cam1/image_raw"], "/imu0")
    with pytest.raises(BagError, match="/nope not in the bag"):
        choose_topics(topics, cams=["/nope"])
    with pytest.raises(BagError, match="needs the IMU"):
        choose_topics({k: v for k, v in topics.items() if k != "/imu0"})
    three = topics | {"/cam2/image_raw": (img, 10)}
    with pytest.raises(BagError, match="--cam LEFT --cam RIGHT"):
        choose_topics(three)
    with pytest.raises(BagError, match="name one with --imu"):
        choose_topics(topics | {"/imu1": (imu, 5)})
    with pytest.raises(BagError, match="not sensor_msgs/Imu"):
        choose_topics(topics, imu="/tf")


@pytest.fixture(scope="module")
def micro():
    return require_real_data("euroc_V1_01_micro", "mav0")


@pytest.mark.unit
def test_kalibr_rig_equals_the_euroc_rig(tmp_path, micro):
    from shared.camera import load_rig
    from services.app.datasets.kalibr import read_kalibr

    chain, imu = write_kalibr(micro, tmp_path, timeshift_s=0.004)
    rig = read_kalibr(chain, imu)
    ref = load_rig(micro)
    assert [c.name for c in rig.cameras] == [c.name for c in ref]
    for a, b in zip(rig.cameras, ref):
        assert np.allclose(a.T_SC, b.T_SC, atol=1e-12)
        assert (a.camera.fx, a.camera.cy, a.camera.distortion) == (b.camera.fx, b.camera.cy, "radtan")
        assert np.allclose(a.camera.dist_coeffs, b.camera.dist_coeffs)
    assert rig.timeshift_ns == [4_000_000, 4_000_000] and rig.topics[0] == "/cam0/image_raw"
    assert rig.imu_yaml["gyroscope_noise_density"] == pytest.approx(1.6968e-04) and rig.imu_topic == "/imu0"


@pytest.mark.parametrize("kind", ["mcap", "sqlite3", "ros1"])
def test_real_frames_round_trip_through_a_bag(tmp_path, micro, kind):
    from shared.euroc_reader import EurocDataset
    from services.app.datasets.bag_input import bag_to_euroc

    name = {"mcap": "bag2", "sqlite3": "bag2db", "ros1": "run.bag"}[kind]
    bag = write_bag(micro, tmp_path / name, kind, max_frames=15)
    assert is_ros_bag(bag)
    chain, imu = write_kalibr(micro, tmp_path / "kalibr")
    counts = bag_to_euroc(bag, tmp_path / "out", chain, imu, progress=False)
    assert counts["frames"] == 15 and counts["cameras"] == "/cam0/image_raw,/cam1/image_raw"
    src, out = EurocDataset(micro), EurocDataset(tmp_path / "out")
    assert np.array_equal(out.frame_stamps_ns, src.frame_stamps_ns[:15])
    for t in out.frame_stamps_ns[[0, 7, 14]]:
        for a, b in zip(out.load_frame(int(t)), src.load_frame(int(t))):
            assert np.array_equal(a, b)  # mono8 and PNG are lossless
    sel = np.isin(src.imu_stamps_ns, out.imu_stamps_ns)
    assert sel.sum() == len(out.imu_stamps_ns) > 200 and np.allclose(out.imu_values, src.imu_values[sel])
    with pytest.raises(FileExistsError):
        bag_to_euroc(bag, tmp_path / "out", chain, imu, progress=False)


def test_sync_tolerance_timeshift_and_missing_calibration(tmp_path, micro):
    from shared.euroc_reader import EurocDataset
    from services.app.datasets.bag_input import bag_to_euroc

    bag = write_bag(micro, tmp_path / "b", "mcap", max_frames=10, cam_delay_ns=(0, 3_000_000))
    chain, imu = write_kalibr(micro, tmp_path / "k", timeshift_s=0.005)
    with pytest.raises(BagError, match="no stereo frame matched"):
        bag_to_euroc(bag, tmp_path / "o1", chain, imu, sync_tolerance_ms=2.0, progress=False)
    counts = bag_to_euroc(bag, tmp_path / "o2", chain, imu, sync_tolerance_ms=4.0, progress=False)
    assert counts["frames"] == 10
    src, out = EurocDataset(micro), EurocDataset(tmp_path / "o2")
    assert np.array_equal(out.frame_stamps_ns, src.frame_stamps_ns[:10] + 5_000_000)  # t_imu = t_cam + shift
    with pytest.raises(BagError, match="no calibration"):
        bag_to_euroc(bag, tmp_path / "o3", None, progress=False)
    with pytest.raises(BagError, match="no IMU noise"):
        bag_to_euroc(bag, tmp_path / "o4", chain, None, progress=False)


def _folder_and_its_bag_trajectories(folder, tmp_path):
    """The offline estimator's (result, causal trajectory) on ``folder`` and on the folder written as a ROS 2 bag
    (mcap, raw mono8 and PNG-compressed images) with a Kalibr calibration, converted back."""
    from services.app.datasets.bag_input import bag_to_euroc
    from tools.vio.offline import run

    bag = write_bag(folder, tmp_path / "bag", "mcap", encodings=("mono8", "png"))
    chain, imu = write_kalibr(folder, tmp_path / "k")
    bag_to_euroc(bag, tmp_path / "out", chain, imu, progress=False)
    return run(str(folder), None, []), run(str(tmp_path / "out"), None, [])


@pytest.mark.e2e
def test_converted_bag_gives_the_same_trajectory(tmp_path, micro):
    (_, a), (_, b) = _folder_and_its_bag_trajectories(micro, tmp_path)
    assert len(a.stamps_ns) > 40 and np.array_equal(a.stamps_ns, b.stamps_ns)
    # the same to a nanometre: the extrinsics went through Kalibr's T_cam_imu and back (inverted twice)
    assert np.abs(a.p_WS - b.p_WS).max() < 1e-9


@pytest.mark.e2e
def test_a_bag_of_a_moving_replica_gives_the_same_trajectory(tmp_path):
    """The same with motion (the micro frames stand still): 5 s of a rendered V1_02 stretch (half resolution,
    simulated IMU)."""
    import e2e_dataset

    data = e2e_dataset.make_dataset(tmp_path / "replica", "V1_02", start_s=0.0, seconds=5.0)
    (ra, a), (_, b) = _folder_and_its_bag_trajectories(data, tmp_path)
    assert len(a.stamps_ns) > 80 and np.array_equal(a.stamps_ns, b.stamps_ns)
    assert np.abs(a.p_WS - b.p_WS).max() < 1e-9
    assert ra["ate_rmse_m"] < 0.05, ra  # and it moved: the trajectory is a real one
    assert np.ptp(a.p_WS, axis=0).max() > 0.3


@pytest.mark.e2e
def test_sigmaslam_run_on_a_ros2_bag(tmp_path, micro):
    """The documented form for bag users, as processes: ``sigmaslam run BAG --calib ... --out DIR``."""
    import json
    import subprocess
    import sys

    from helpers_zenoh import REPO, child_env

    bag = write_bag(micro, tmp_path / "bag", "mcap", encodings=("mono8", "mono8"))
    chain, imu = write_kalibr(micro, tmp_path / "k")
    services = "supervisor.services=[{name: frontend, argv: [frontend]}, {name: backend, argv: [backend]}]"
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "services.app.cli", "run", str(bag), "--calib", str(chain),
                           "--imu-calib", str(imu), "--gt", str(micro / "groundtruth_tum.txt"), "--out", str(out),
                           "--set", services, "--timeout-s", "300", "--ros2-bag", str(tmp_path / "results")],
                          cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=600)
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log[-3000:]
    assert "converted" in log and (out / "dataset" / "mav0" / "cam1" / "data.csv").is_file()
    # the player waited for every service it started (the recorder too) by its heartbeat, not for a time-out
    assert "not seen within" not in log, log[-3000:]
    stats = json.loads((out / "stats.json").read_text())
    assert stats["frames_sent"] == 60, stats
    ate = json.loads((out / "ate.json").read_text())
    assert ate["ate_rmse_m"] < 0.02, ate
    # the results handed back as a ROS 2 bag: one Odometry per published pose, the final path
    from rosbags.highlevel import AnyReader

    with AnyReader([tmp_path / "results"]) as r:
        n = {c.topic: c.msgcount for c in r.connections}
    assert n["/sigmaslam/odom"] == ate["poses"] and n["/tf"] >= ate["poses"] and n["/sigmaslam/path"] >= 1, n
    bad = subprocess.run([sys.executable, "-m", "services.app.cli", "run", str(bag), "--out", str(tmp_path / "x")],
                         cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "no calibration" in bad.stdout + bad.stderr
