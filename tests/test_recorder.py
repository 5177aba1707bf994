"""MCAP recorder: a real `sigmaslam record` process on a real Zenoh network (loopback, free port).

Checks: every published message comes back equal from read_recording, the config is in the
metadata, the file has a summary, Foxglove mirror channels decode with the protobuf classes, and a
SIGKILLed recording is recoverable up to its last completed chunk.
"""

from __future__ import annotations

import dataclasses
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import yaml
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.reader import make_reader

from helpers_zenoh import REPO, child_env, router, wait_for, wait_for_heartbeat
from services.recorder.mcap_reader import read_metadata, read_recording
from services.recorder.recovery import recover
from services.app.cli import main as cli_main
from shared import messages as m, topics
from shared.config import to_dict
from transport.pubsub import Publisher
from transport.session import open_session

RNG = np.random.default_rng(7)


def _hdr(i: int, frame: str = "W") -> m.Header:
    return m.Header(stamp_ns=1_700_000_000_000_000_000 + i * 33_000_000, seq=i, frame_id=frame)


def make_messages(n: int) -> dict[str, list]:
    """Messages of several types per relative key (images large enough for shared memory)."""
    out: dict[str, list] = {t.key: [] for t in (topics.IMU, topics.FRAME, topics.STATE, topics.DEPTH_FUSED, topics.SUBMAP,
                                                topics.LANDMARKS)}
    for i in range(n):
        out[topics.IMU.key].append(m.ImuSample(header=_hdr(i, "S"), omega_S=RNG.normal(size=3), acc_S=RNG.normal(size=3)))
        out[topics.FRAME.key].append(m.MultiCameraFrame(
            header=_hdr(i), images=tuple(RNG.integers(0, 255, (240, 320), dtype=np.uint8) for _ in range(2)),
            camera_names=("cam0", "cam1"), stamps_ns=np.array([i, i + 1], np.int64)))
        T = np.eye(4)
        T[:3, :3] = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]])  # 90 deg about z
        T[:3, 3] = [i, 2.0, -1.0]
        out[topics.STATE.key].append(m.EstimatorState(header=_hdr(i), T_WS=T, v_W=RNG.normal(size=3),
                                                      gyro_bias=np.zeros(3), acc_bias=np.zeros(3), covariance=np.eye(15)))
        depth = RNG.uniform(0.5, 5, (24, 32)).astype(np.float32)
        depth[0, 0] = np.nan
        out[topics.DEPTH_FUSED.key].append(m.DepthFrame(header=_hdr(i, "cam0"), depth=depth, sigma=depth * 0.1,
                                                        K=np.eye(3), T_WC=np.eye(4), source="fused"))
        if i % 3 == 0:
            k = 5 + i
            out[topics.LANDMARKS.key].append(m.Landmarks(
                header=_hdr(i), ids=np.arange(k, dtype=np.int64) + 100 * i, p_W=RNG.normal(size=(k, 3)),
                num_observations=RNG.integers(2, 9, k).astype(np.int32), last_seen_ns=np.full(k, i, np.int64)))
    out[topics.SUBMAP.key].append(m.SubmapMesh(
        header=_hdr(0), submap_id=4, T_WM=np.eye(4), vertices_M=RNG.normal(size=(6, 3)).astype(np.float32),
        faces=np.array([[0, 1, 2], [3, 4, 5]], np.int32), vertex_colors=np.full((6, 3), 255, np.uint8)))
    return out


def same(a, b) -> bool:
    if type(a) is not type(b) or a.header != b.header:
        return False
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            if not np.array_equal(x, y, equal_nan=x.dtype.kind == "f"):
                return False
        elif isinstance(x, tuple) and x and isinstance(x[0], np.ndarray):
            if len(x) != len(y) or not all(np.array_equal(p, q) for p, q in zip(x, y)):
                return False
        elif x != y:
            return False
    return True


def write_config(tmp_path, tcfg, **recorder) -> str:
    data = {"transport": to_dict(tcfg) | {"stats_period_s": 0.2, "heartbeat_period_s": 0.2}, "recorder": recorder}
    path = tmp_path / "system.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


def start_recorder(tcfg, cfg_path: str, out) -> tuple[subprocess.Popen, list[str]]:
    """Start `sigmaslam record`; returns once its node heartbeats 'running' (publish_all then waits for its
    subscriber to match each publisher)."""
    proc = subprocess.Popen([sys.executable, "-m", "services.app.cli", "record", cfg_path, "--out", str(out)],
                            cwd=REPO, env=child_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")), daemon=True).start()
    with open_session(tcfg) as session:
        ok = wait_for_heartbeat(session, tcfg, "recorder", 30.0, proc)
    assert ok and proc.poll() is None, "".join(lines)
    return proc, lines


def publish_all(tcfg, msgs: dict[str, list]) -> dict[str, list]:
    """Publish round-robin over the keys; returns the sent messages per full key."""
    sent: dict[str, list] = {}
    with open_session(tcfg) as session:
        pubs = {k: Publisher(session, f"{tcfg.namespace}/{k}", type(v[0]), tcfg, block=True) for k, v in msgs.items()}
        for pub in pubs.values():
            assert pub.wait_for_subscribers(10.0)
        for i in range(max(len(v) for v in msgs.values())):
            for k, v in msgs.items():
                if i < len(v):
                    pubs[k].publish(v[i])
                    sent.setdefault(pubs[k].key_expr, []).append(v[i])
            time.sleep(0.005)
        time.sleep(1.0)  # let the recorder receive the last ones
        for pub in pubs.values():
            pub.close()
    return sent


def check_all_present(path, sent: dict[str, list]) -> None:
    got: dict[str, list] = {}
    for key, log_ns, msg in read_recording(path):
        assert log_ns > 1_600_000_000 * 10**9  # receive time, Unix epoch ns
        got.setdefault(key, []).append(msg)
    for key, msgs in sent.items():
        assert len(got.get(key, [])) == len(msgs), key
        assert all(same(a, b) for a, b in zip(got[key], msgs)), key


def test_record_sigterm_complete_file(tmp_path):
    out = tmp_path / "run.mcap"
    with router() as tcfg:
        cfg_path = write_config(tmp_path, tcfg, chunk_size_bytes=256 * 1024)
        proc, lines = start_recorder(tcfg, cfg_path, out)
        try:
            sent = publish_all(tcfg, make_messages(12))
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=20)
        finally:
            proc.kill()
    assert proc.returncode == 0, "".join(lines)
    check_all_present(out, sent)
    ns = tcfg.namespace
    # the recorder's own stats/heartbeat are recorded too (everything under the namespace)
    assert any(k == f"{ns}/heartbeat/recorder" for k, _, _ in read_recording(out, topics=[f"{ns}/heartbeat/recorder"]))
    meta = read_metadata(out)
    assert meta["transport"]["namespace"] == ns and meta["recorder"]["chunk_size_bytes"] == 256 * 1024

    with open(out, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count > 5 * 12
        assert summary.statistics.chunk_count >= 2
        schemas = {c.topic: summary.schemas[c.schema_id] for c in summary.channels.values()}
        assert schemas[f"{ns}/{topics.STATE.key}"].name == "EstimatorState"
        assert schemas[f"{ns}/{topics.STATE.key}"].encoding == "sigmaslam-codec-v1"
        assert schemas[f"foxglove/{ns}/{topics.FRAME.key}/cam1"].name == "foxglove.RawImage"
        assert schemas[f"foxglove/{ns}/{topics.FRAME.key}/cam1"].encoding == "protobuf"
        frames = sent[f"{ns}/{topics.FRAME.key}"]
        states = sent[f"{ns}/{topics.STATE.key}"]
        images, poses, scenes, depths, clouds = [], [], [], [], []
        for _schema, channel, message in reader.iter_messages(topics=[
                f"foxglove/{ns}/{topics.FRAME.key}/cam1", f"foxglove/{ns}/{topics.STATE.key}",
                f"foxglove/{ns}/{topics.SUBMAP.key}", f"foxglove/{ns}/{topics.DEPTH_FUSED.key}/depth",
                f"foxglove/{ns}/{topics.LANDMARKS.key}"]):
            if channel.topic.endswith(topics.LANDMARKS.key):
                clouds.append(PointCloud.FromString(message.data))
            elif channel.topic.endswith("cam1"):
                images.append(RawImage.FromString(message.data))
            elif channel.topic.endswith("depth"):
                depths.append(RawImage.FromString(message.data))
            elif channel.topic.endswith(topics.STATE.key):
                poses.append(PoseInFrame.FromString(message.data))
            else:
                scenes.append(SceneUpdate.FromString(message.data))
    assert len(images) == len(frames) and len(poses) == len(states) and len(scenes) == 1 and len(depths) == 12
    img = images[3]
    assert (img.width, img.height, img.encoding, img.frame_id) == (320, 240, "mono8", "cam1")
    assert np.array_equal(np.frombuffer(img.data, np.uint8).reshape(240, 320), frames[3].images[1])
    assert img.timestamp.seconds * 10**9 + img.timestamp.nanos == frames[3].header.stamp_ns
    d = depths[5]
    assert d.encoding == "32FC1" and d.step == 32 * 4
    want = sent[f"{ns}/{topics.DEPTH_FUSED.key}"][5].depth
    assert np.array_equal(np.frombuffer(d.data, "<f4").reshape(24, 32), want, equal_nan=True)
    p = poses[7].pose
    assert (p.position.x, p.position.y, p.position.z) == (7.0, 2.0, -1.0)
    s = np.sqrt(0.5)  # 90 deg about z: (x, y, z, w) = (0, 0, sin 45, cos 45)
    assert np.allclose([p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w], [0, 0, s, s])
    lms = sent[f"{ns}/{topics.LANDMARKS.key}"]
    assert len(clouds) == len(lms) == 4 and clouds[2].frame_id == "W" and [f.name for f in clouds[2].fields] == list("xyz")
    np.testing.assert_allclose(np.frombuffer(clouds[2].data, "<f4").reshape(-1, 3), lms[2].p_W, rtol=1e-6, atol=1e-6)
    tri = scenes[0].entities[0].triangles[0]
    assert scenes[0].entities[0].id == "submap4" and list(tri.indices) == [0, 1, 2, 3, 4, 5] and len(tri.points) == 6


def test_record_sigterm_as_soon_as_the_file_exists_leaves_a_complete_file(tmp_path):
    """A stop signal that arrives the moment the file appears (a supervisor stopping a freshly restarted
    recorder) is handled: the file gets its summary and metadata instead of being cut by the default action."""
    out = tmp_path / "early.mcap"
    with router() as tcfg:
        cfg_path = write_config(tmp_path, tcfg)
        proc = subprocess.Popen([sys.executable, "-m", "services.app.cli", "record", cfg_path, "--out", str(out)],
                                cwd=REPO, env=child_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        try:
            assert wait_for(lambda: out.exists() or proc.poll() is not None, 30.0, interval=0.001)
            proc.send_signal(signal.SIGTERM)
            text, _ = proc.communicate(timeout=20)
        finally:
            proc.kill()
    assert proc.returncode == 0, text
    assert read_metadata(out)["transport"]["namespace"] == tcfg.namespace


def test_record_sigkill_recoverable(tmp_path):
    out, fixed = tmp_path / "killed.mcap", tmp_path / "fixed.mcap"
    n = 60
    with router() as tcfg:
        # small chunks, no timed flush: what is on disk is exactly the completed chunks
        cfg_path = write_config(tmp_path, tcfg, chunk_size_bytes=4096, flush_period_s=1000.0, foxglove=False)
        proc, _lines = start_recorder(tcfg, cfg_path, out)
        try:
            sent = publish_all(tcfg, {topics.IMU.key: make_messages(n)[topics.IMU.key]})
            proc.kill()
            proc.wait(timeout=10)
        finally:
            proc.kill()
    data = out.read_bytes()
    assert not data.endswith(b"\x89MCAP0\r\n")  # no footer: the file was cut
    with pytest.raises(Exception):
        list(read_recording(out))

    assert cli_main(["record", "--recover", str(out), "--out", str(fixed)]) == 0
    key = f"{tcfg.namespace}/{topics.IMU.key}"
    got = [msg for _, _, msg in read_recording(fixed, topics=[key])]
    want = sent[key]
    # a 4 KiB chunk holds < 15 IMU samples (~300 B each): all but the chunk in progress survive, in order
    assert n - 15 <= len(got) <= n
    assert all(same(a, b) for a, b in zip(got, want))
    assert read_metadata(fixed)["recorder"]["chunk_size_bytes"] == 4096
    # recovering the recovered (complete) file changes nothing
    report = recover(fixed, tmp_path / "again.mcap")
    assert report.complete and report.messages >= len(got)
