"""Player service over real Zenoh (rate, lockstep, pause/resume/stop, MCAP source) and sigmaslam convert."""
from __future__ import annotations

import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import yaml

from helpers_zenoh import REPO, child_env, router, wait_for
from services.player.source import McapSource, open_source
from shared import topics
from shared.codec import Header
from shared.config import to_dict
from shared.euroc_reader import DatasetError, EurocDataset
from shared.euroc_writer import write_euroc
from shared.messages import Control, EstimatorState
from tools.dataset_convert import euroc_to_mcap, mcap_to_euroc
from transport.node import Node
from transport.queues import Empty

T0 = 1_403_715_523_912_143_104
N_FRAMES = 10


def _cam_yaml(name: str, tx: float) -> dict:
    T = np.eye(4)
    T[0, 3] = tx
    return {"sensor_type": "camera", "comment": name, "T_BS": {"cols": 4, "rows": 4, "data": T.ravel().tolist()},
            "rate_hz": 20, "resolution": [40, 30], "camera_model": "pinhole", "intrinsics": [30.0, 30.0, 20.0, 15.0],
            "distortion_model": "radial-tangential", "distortion_coefficients": [0.01, 0.0, 0.0, 0.0]}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """A tiny two-camera EuRoC folder: 10 frames at 20 Hz, IMU at 200 Hz, plus GT and a depth file."""
    root = tmp_path_factory.mktemp("ds") / "tiny"
    rng = np.random.default_rng(0)
    frames = [(T0 + i * 50_000_000, [rng.integers(0, 255, (30, 40), dtype=np.uint8) for _ in range(2)])
              for i in range(N_FRAMES)]
    t_imu = T0 - 20_000_000 + np.arange(110, dtype=np.int64) * 5_000_000
    imu = np.column_stack([t_imu, rng.normal(size=(110, 6))])
    write_euroc(root, {"cam0": _cam_yaml("cam0", 0.0), "cam1": _cam_yaml("cam1", 0.1)}, frames, imu,
                {"sensor_type": "imu", "rate_hz": 200}, imu_stamps_ns=t_imu)
    gt = root / "mav0" / "state_groundtruth_estimate0"
    gt.mkdir()
    (gt / "data.csv").write_text("#t,p,q\n" + "".join(f"{t},0,0,0,1,0,0,0\n" for t in t_imu[::10]))
    return root


def _config(tmp_path, tcfg, **player) -> str:
    data = {"transport": to_dict(tcfg) | {"stats_period_s": 0.2, "heartbeat_period_s": 0.2}, "player": player}
    path = tmp_path / "system.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


def _start_player(cfg: str, dataset, *extra: str) -> tuple[subprocess.Popen, list[str]]:
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "player", str(dataset), cfg, "--wait-for", "tester",
                             *extra], cwd=REPO, env=child_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    lines: list[str] = []
    threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")), daemon=True).start()
    return proc, lines


class Collector:
    """The test's own node: receives the player's topics with receive times."""

    def __init__(self, node: Node):
        self.imu, self.frames, self.ends = [], [], []
        node.subscriber(topics.IMU, handler=lambda m: self.imu.append(m))
        node.subscriber(topics.FRAME, policy="all", depth=100, handler=lambda m: self.frames.append((time.monotonic(), m)))
        node.subscriber(topics.STREAM_END, handler=lambda m: self.ends.append(m))


def _finish(proc, lines, timeout=30.0):
    try:
        proc.wait(timeout=timeout)
    finally:
        proc.kill()
    assert proc.returncode == 0, "".join(lines)


def test_rate_mode_publishes_everything_in_time(tmp_path, dataset):
    with router() as tcfg:
        cfg = _config(tmp_path, tcfg, mode="rate", rate=0.5)
        with Node("tester", tcfg) as node:
            col = Collector(node)
            proc, lines = _start_player(cfg, dataset)
            assert wait_for(lambda: col.ends, 40.0), "".join(lines)
            _finish(proc, lines)
    assert len(col.imu) == 110 and len(col.frames) == N_FRAMES
    assert col.ends[0].frames_sent == N_FRAMES and col.ends[0].header.stamp_ns == T0 + 9 * 50_000_000
    span = col.frames[-1][0] - col.frames[0][0]
    print(f"rate 0.5: 9 frame intervals of 50 ms took {span:.3f} s (expected 0.9 s)")
    assert 0.75 < span < 1.5
    assert [m.header.seq for _, m in col.frames] == list(range(N_FRAMES))
    assert col.frames[0][1].camera_names == ("cam0", "cam1")


def test_lockstep_waits_for_the_estimator(tmp_path, dataset):
    with router() as tcfg:
        cfg = _config(tmp_path, tcfg, mode="lockstep", lockstep_timeout_s=10.0)
        with Node("tester", tcfg) as node:
            col = Collector(node)
            state_pub = node.publisher(topics.STATE)
            proc, lines = _start_player(cfg, dataset)
            answered, outstanding_max = 0, 0
            deadline = time.monotonic() + 40
            while not col.ends and time.monotonic() < deadline:
                if len(col.frames) > answered:
                    outstanding_max = max(outstanding_max, len(col.frames) - answered)
                    time.sleep(0.15)  # a slow estimator
                    outstanding_max = max(outstanding_max, len(col.frames) - answered)
                    stamp = col.frames[answered][1].header.stamp_ns
                    state_pub.publish(EstimatorState(header=Header(stamp_ns=stamp, seq=answered, frame_id="W"),
                                                     T_WS=np.eye(4), v_W=np.zeros(3), gyro_bias=np.zeros(3),
                                                     acc_bias=np.zeros(3), covariance=np.eye(15)))
                    answered += 1
                time.sleep(0.005)
            _finish(proc, lines)
    assert len(col.frames) == N_FRAMES and answered == N_FRAMES
    assert outstanding_max == 1  # never a second frame before the first was answered
    assert "0 lockstep timeouts" in "".join(lines)


def test_pause_resume_stop(tmp_path, dataset):
    with router() as tcfg:
        cfg = _config(tmp_path, tcfg, mode="rate", rate=0.1, start_paused=True)
        with Node("tester", tcfg) as node:
            col = Collector(node)
            ctl = node.publisher(topics.CONTROL)
            proc, lines = _start_player(cfg, dataset)
            time.sleep(3.0)
            assert not col.frames and not col.imu and proc.poll() is None  # paused
            ctl.publish(Control(header=Header(stamp_ns=0, seq=0, frame_id=""), target="player", command="resume"))
            assert wait_for(lambda: len(col.frames) >= 2, 10.0), "".join(lines)
            ctl.publish(Control(header=Header(stamp_ns=0, seq=1, frame_id=""), target="*", command="pause"))
            time.sleep(0.5)
            n = len(col.frames)
            time.sleep(1.0)
            assert len(col.frames) == n  # nothing while paused (0.5 s/frame at rate 0.1)
            ctl.publish(Control(header=Header(stamp_ns=0, seq=2, frame_id=""), target="player", command="stop"))
            assert wait_for(lambda: col.ends, 10.0), "".join(lines)
            _finish(proc, lines)
    assert col.ends[0].frames_sent == len(col.frames) < N_FRAMES


def test_convert_round_trip_and_mcap_playback(tmp_path, dataset):
    mcap = tmp_path / "tiny.mcap"
    counts = euroc_to_mcap(dataset, mcap)
    assert counts["imu"] == 110 and counts["frames"] == N_FRAMES and counts["attachments"] >= 4
    back = tmp_path / "back"
    mcap_to_euroc(mcap, back)
    a, b = EurocDataset(dataset), EurocDataset(back)
    np.testing.assert_array_equal(a.frame_stamps_ns, b.frame_stamps_ns)
    np.testing.assert_array_equal(a.imu_stamps_ns, b.imu_stamps_ns)
    np.testing.assert_array_equal(a.imu_values, b.imu_values)
    for t in a.frame_stamps_ns:
        for x, y in zip(a.load_frame(t), b.load_frame(t)):
            np.testing.assert_array_equal(x, y)
    for rel in ("mav0/cam1/sensor.yaml", "mav0/state_groundtruth_estimate0/data.csv"):
        assert (dataset / rel).read_bytes() == (back / rel).read_bytes()
    # the MCAP is a player source with the same messages, in the same order
    src = open_source(mcap)
    assert isinstance(src, McapSource)
    got = [(type(m).__name__, m.header.stamp_ns) for m in src.messages()]
    assert got == [(type(m).__name__, m.header.stamp_ns) for m in EurocDataset(dataset).messages()]
    # CLI: EuRoC -> MCAP -> EuRoC
    res = subprocess.run([sys.executable, "-m", "services.cli", "convert", str(mcap), str(tmp_path / "cli")],
                         cwd=REPO, env=child_env(), capture_output=True, text=True)
    assert res.returncode == 0 and "frames 10" in res.stdout, res.stderr


def test_error_paths(tmp_path, dataset):
    with pytest.raises(DatasetError):
        open_source(tmp_path / "nothing")
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap")
    with pytest.raises(DatasetError, match="not an MCAP"):
        open_source(tmp_path / "junk.mcap")
    mcap = tmp_path / "t.mcap"
    euroc_to_mcap(dataset, mcap)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])
    with pytest.raises(DatasetError, match="recover"):
        list(open_source(cut).messages())
    with pytest.raises(FileExistsError):
        mcap_to_euroc(mcap, dataset)
    # unreadable image and backwards stamp: counted skips, the rest still plays
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(dataset, bad)
    (bad / "mav0" / "cam0" / "data" / f"{T0 + 50_000_000}.png").write_bytes(b"garbage")
    csv = bad / "mav0" / "imu0" / "data.csv"
    lines = csv.read_text().splitlines()
    lines.insert(5, lines[2])
    csv.write_text("\n".join(lines) + "\n")
    ds = EurocDataset(bad)
    msgs = list(ds.messages())
    assert ds.stats["unreadable_images"] == 1 and ds.stats["backwards_stamps"] == 1
    assert sum(type(m).__name__ == "MultiCameraFrame" for m in msgs) == N_FRAMES - 1
    res = subprocess.run([sys.executable, "-m", "services.cli", "player", str(tmp_path / "nothing")], cwd=REPO,
                         env=child_env(), capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and "not found" in res.stdout + res.stderr
    res = subprocess.run([sys.executable, "-m", "services.cli", "convert", str(tmp_path / "nothing"), str(tmp_path / "o.mcap")],
                         cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=60)
    assert res.returncode == 1 and "not found" in res.stderr
