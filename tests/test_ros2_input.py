"""Live ROS 2 input (issue 58): the assembler turns a robot's rmw_zenoh samples into the pipeline's sensor messages
and counts what it cannot use (wrong type hash, unknown encoding, no IMU stream, out-of-order stamps, truncated CDR,
wrong image size) without raising; the player as a stand-in robot (--as-ros2) read back by ``sigmaslam ros2_input``
as processes gives the dataset's own images, stamps and IMU samples."""

from __future__ import annotations

import subprocess
import sys
import threading

import numpy as np
import pytest
import yaml

from shared import messages as m
from shared import ros2_sensors as rs
from shared import ros2_wire as wire
from shared.camera import CameraCalib, CameraModel
from shared.config import to_dict

W, H = 40, 30


def _rig():
    return [CameraCalib(f"cam{i}", CameraModel(width=W, height=H, fx=30, fy=30, cx=20, cy=15)) for i in range(2)]


def _asm(clock=None):
    from services.ros2_input.assembler import SensorAssembler

    t = [100.0]
    asm = SensorAssembler(_rig(), ["/r/cam0/image_raw", "/r/cam1/image_raw/compressed"], "/r/imu0",
                          sync_tolerance_ms=2.0, clock=clock or (lambda: t[0]))
    return asm, t


def _sample(topic: str, ros_type: str, msg) -> tuple:
    ts = wire.type_store()
    return topic, wire.dds_type_name(ros_type), wire.type_hash(ros_type), bytes(ts.serialize_cdr(msg, ros_type))


def _imu(ns: int, w=(0.1, -0.2, 0.3), a=(0.0, 0.0, 9.81)):
    s = m.ImuSample(header=m.Header(stamp_ns=ns), omega_S=np.array(w), acc_S=np.array(a))
    return _sample("/r/imu0", rs.IMU_TYPE, rs.imu_msg(wire.type_store(), s, "imu"))


def _img(cam: int, ns: int, grey, encoding="mono8"):
    ts = wire.type_store()
    if cam == 1:
        return _sample("/r/cam1/image_raw/compressed", rs.COMPRESSED_TYPE, rs.compressed_msg(ts, ns, "cam1", grey))
    return _sample("/r/cam0/image_raw", rs.IMAGE_TYPE, rs.image_msg(ts, ns, "cam0", grey, encoding))


def _grey(seed: int):
    return np.random.default_rng(seed).integers(0, 255, (H, W), dtype=np.uint8)


@pytest.mark.unit
def test_samples_become_imu_and_paired_frames():
    asm, t = _asm()
    out = asm.on_sample(*_imu(1_000_000_000))
    assert isinstance(out[0], m.ImuSample) and out[0].header.stamp_ns == 1_000_000_000
    np.testing.assert_array_equal(out[0].omega_S, [0.1, -0.2, 0.3])
    frames = []
    for k in range(3):
        ns = 1_000_000_000 + k * 50_000_000
        g0, g1 = _grey(2 * k), _grey(2 * k + 1)
        # bgr8 from the first camera: grey again; the second camera 1 ms later as PNG (lossless)
        assert asm.on_sample(*_img(0, ns, g0, "bgr8")) == []
        frames += asm.on_sample(*_img(1, ns + 1_000_000, g1))
        f = frames[-1]
        assert f.header.stamp_ns == ns and f.stamps_ns.tolist() == [ns, ns + 1_000_000]
        np.testing.assert_array_equal(f.images[0], g0)
        np.testing.assert_array_equal(f.images[1], g1)
        assert f.camera_names == ("cam0", "cam1")
    assert [f.header.seq for f in frames] == [0, 1, 2] and not any(asm.drops.values())


@pytest.mark.unit
def test_bad_input_is_a_counted_drop_never_an_exception():
    asm, t = _asm()
    asm.on_sample(*_imu(1_000_000_000))
    # a publisher of another type hash (another distro's definition) on the IMU topic
    topic, dds, _, payload = _imu(1_100_000_000)
    assert asm.on_sample(topic, dds, "RIHS01_" + "0" * 64, payload) == [] and asm.drops["wrong_type"] == 1
    # a publisher of another type altogether on a camera topic
    assert asm.on_sample("/r/cam0/image_raw", *_imu(1_100_000_000)[1:]) == [] and asm.drops["wrong_type"] == 2
    # truncated CDR
    topic, dds, h, payload = _img(0, 1_000_000_000, _grey(0))
    assert asm.on_sample(topic, dds, h, payload[: len(payload) // 3]) == [] and asm.drops["bad_cdr"] == 1
    assert asm.on_sample(*_imu(1_200_000_000)[:3], b"\x00\x01") == [] and asm.drops["bad_cdr"] == 2
    # an encoding it does not read
    ts = wire.type_store()
    yuv = ts.types[rs.IMAGE_TYPE](header=ts.types["std_msgs/msg/Header"](
        stamp=ts.types["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="cam0"), height=H, width=W,
        encoding="yuv422", is_bigendian=0, step=2 * W, data=np.zeros(2 * W * H, np.uint8))
    assert asm.on_sample(*_sample("/r/cam0/image_raw", rs.IMAGE_TYPE, yuv)) == [] and asm.drops["encoding"] == 1
    # an image of another size than the rig's
    assert asm.on_sample(*_img(0, 1_000_000_000, np.zeros((H, W + 2), np.uint8))) == []
    assert asm.drops["image_size"] == 1
    # out-of-order stamps: IMU and images
    asm.on_sample(*_imu(1_300_000_000))
    assert asm.on_sample(*_imu(1_250_000_000)) == [] and asm.drops["out_of_order"] == 1
    asm.on_sample(*_img(0, 1_400_000_000, _grey(1)))
    assert asm.on_sample(*_img(0, 1_350_000_000, _grey(1))) == [] and asm.drops["out_of_order"] == 2
    assert len(asm.on_sample(*_img(1, 1_400_000_000, _grey(2)))) == 1  # still pairs after all that


@pytest.mark.unit
def test_frames_without_an_imu_stream_are_dropped_and_said_so(caplog):
    asm, t = _asm()
    assert asm.on_sample(*_img(0, 1_000_000_000, _grey(0))) == []
    assert asm.on_sample(*_img(1, 1_000_000_000, _grey(1))) == []
    assert asm.drops["no_imu"] == 1 and "no IMU sample on /r/imu0" in caplog.text
    asm.on_sample(*_imu(1_010_000_000))
    asm.on_sample(*_img(0, 1_050_000_000, _grey(0)))
    assert len(asm.on_sample(*_img(1, 1_050_000_000, _grey(1)))) == 1
    t[0] += 5.0  # the IMU driver stopped 5 s ago
    asm.on_sample(*_img(0, 1_100_000_000, _grey(0)))
    assert asm.on_sample(*_img(1, 1_100_000_000, _grey(1))) == [] and asm.drops["no_imu"] == 2


@pytest.mark.unit
def test_unpaired_images_are_dropped_when_a_later_frame_pairs():
    asm, t = _asm()
    asm.on_sample(*_imu(900_000_000))
    asm.on_sample(*_img(0, 1_000_000_000, _grey(0)))  # its partner never comes
    asm.on_sample(*_img(0, 1_050_000_000, _grey(1)))
    out = asm.on_sample(*_img(1, 1_050_500_000, _grey(2)))
    assert len(out) == 1 and out[0].header.stamp_ns == 1_050_000_000 and asm.drops["unpaired"] == 1
    assert asm.on_sample(*_img(1, 1_200_000_000, _grey(3))) == []  # 0.15 s from any cam0 image: waits


@pytest.mark.service
def test_stand_in_robot_through_ros2_input_gives_the_dataset(tmp_path, default_replica):
    """player --as-ros2 (PNG-compressed second camera) -> Zenoh (rmw_zenoh keys) -> sigmaslam ros2_input ->
    sensors/frame and sensors/imu: the dataset's own images, stamps and IMU samples."""
    from helpers_zenoh import REPO, child_env, router, wait_for, wait_for_heartbeat
    from shared import topics
    from shared.euroc_reader import EurocDataset
    from transport.pubsub import Subscriber
    from transport.session import open_session

    n = 12
    with router() as tcfg:
        cfg = {"transport": to_dict(tcfg) | {"stats_period_s": 0.2, "heartbeat_period_s": 0.2},
               "rig": {"calibration": str(default_replica)},
               "ros2": {"domain_id": 5, "input": {"namespace": "/bot", "topics": {
                   "cameras": ["cam0/image_raw", "cam1/image_raw/compressed"], "imu": "imu0"}}}}
        path = tmp_path / "system.yaml"
        path.write_text(yaml.safe_dump(cfg))
        procs, lines = [], []

        def start(*argv):
            p = subprocess.Popen([sys.executable, "-m", "services.app.cli", *argv], cwd=REPO, env=child_env(),
                                 stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            threading.Thread(target=lambda: lines.extend(iter(p.stdout.readline, "")), daemon=True).start()
            procs.append(p)
            return p

        try:
            with open_session(tcfg) as s:
                frames, imus = [], []
                sf = Subscriber(s, f"{tcfg.namespace}/{topics.FRAME.key}", m.MultiCameraFrame, "all", 256,
                                handler=frames.append)
                si = Subscriber(s, f"{tcfg.namespace}/{topics.IMU.key}", m.ImuSample, "all", 100000,
                                handler=imus.append)
                inp = start("ros2_input", str(path))
                assert wait_for_heartbeat(s, tcfg, "ros2_input", 30.0, inp), "".join(lines)
                player = start("player", str(default_replica), str(path), "--as-ros2", "--rate", "2",
                               "--max-frames", str(n), "--wait-for", "ros2_input")
                assert player.wait(timeout=120) == 0, "".join(lines)
                assert wait_for(lambda: len(frames) >= n - 1, 10.0), (len(frames), "".join(lines))
                sf.close()
                si.close()
        finally:
            for p in procs:
                p.terminate()
                p.wait(timeout=20)
    assert all(p.returncode == 0 for p in procs), "".join(lines)
    truth = [msg for msg in EurocDataset(default_replica).messages() if isinstance(msg, m.MultiCameraFrame)][:n]
    by_stamp = {f.header.stamp_ns: f for f in frames}
    assert len(by_stamp) >= n - 1  # the first may go before the IMU stream is seen (a counted no_imu drop)
    for f in truth:
        if f.header.stamp_ns in by_stamp:
            got = by_stamp[f.header.stamp_ns]
            assert got.camera_names == f.camera_names
            for a, b in zip(got.images, f.images):
                np.testing.assert_array_equal(a, b)
    assert len(imus) > 10 * (n - 2) and all(np.diff([i.header.stamp_ns for i in imus]) > 0)
    assert "dropped: none" in "".join(lines) or "no_imu 1" in "".join(lines), "".join(lines)
