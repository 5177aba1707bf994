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
from services.app.datasets.euroc_writer import write_euroc
from shared.messages import Control, EstimatorState, MultiCameraFrame
from services.app.datasets.convert_cmd import euroc_to_mcap, mcap_to_euroc
from transport.node import Node

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
    proc = subprocess.Popen([sys.executable, "-m", "services.app.cli", "player", str(dataset), cfg, "--wait-for", "tester",
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


def _answer(state_pub, stamp_ns: int, seq: int) -> None:
    """The estimator's answer to the frame stamped ``stamp_ns`` (what a lockstep player waits for)."""
    state_pub.publish(EstimatorState(header=Header(stamp_ns=stamp_ns, seq=seq, frame_id="W"), T_WS=np.eye(4),
                                     v_W=np.zeros(3), gyro_bias=np.zeros(3), acc_bias=np.zeros(3),
                                     covariance=np.eye(15)))


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
                    _answer(state_pub, stamp, answered)
                    answered += 1
                time.sleep(0.005)
            _finish(proc, lines)
    assert len(col.frames) == N_FRAMES and answered == N_FRAMES
    assert outstanding_max == 1  # never a second frame before the first was answered
    assert "0 lockstep timeouts" in "".join(lines)


def test_lockstep_plays_the_imu_sample_after_each_frame_before_waiting(tmp_path, dataset):
    """IMU samples that never fall on a frame's stamp (a simulated IMU's own clock): the estimator integrates up to
    the frame, so it answers a frame only once a sample at or after it came; the player must send that sample
    before it waits for the answer, or every frame waits out the lockstep timeout."""
    root = tmp_path / "offset"
    src = EurocDataset(dataset)
    frames = [(int(t), [np.zeros((30, 40), np.uint8)] * 2) for t in src.frame_stamps_ns]
    t_imu = src.imu_stamps_ns + 2_000_000  # 2 ms after each frame, never on one
    assert not np.isin(src.frame_stamps_ns, t_imu).any()
    write_euroc(root, {"cam0": _cam_yaml("cam0", 0.0), "cam1": _cam_yaml("cam1", 0.1)}, frames,
                np.column_stack([t_imu, src.imu_values]), {"sensor_type": "imu", "rate_hz": 200}, imu_stamps_ns=t_imu)
    with router() as tcfg:
        cfg = _config(tmp_path, tcfg, mode="lockstep", lockstep_timeout_s=2.0)
        with Node("tester", tcfg) as node:
            col = Collector(node)
            state_pub = node.publisher(topics.STATE)
            proc, lines = _start_player(cfg, root)
            answered = 0
            deadline = time.monotonic() + 60
            while not col.ends and time.monotonic() < deadline:
                if len(col.frames) > answered:
                    stamp = col.frames[answered][1].header.stamp_ns
                    if any(m.header.stamp_ns >= stamp for m in list(col.imu)):  # what the fast path waits for
                        _answer(state_pub, stamp, answered)
                        answered += 1
                time.sleep(0.005)
            _finish(proc, lines)
    assert len(col.frames) == N_FRAMES and answered == N_FRAMES
    assert "0 lockstep timeouts" in "".join(lines), "".join(lines)
    assert len(col.imu) == len(t_imu)  # every sample once, none held back or sent twice
    assert [m.header.stamp_ns for m in col.imu] == sorted(m.header.stamp_ns for m in col.imu)


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
    res = subprocess.run([sys.executable, "-m", "services.app.cli", "convert", str(mcap), str(tmp_path / "cli")],
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
    res = subprocess.run([sys.executable, "-m", "services.app.cli", "player", str(tmp_path / "nothing")], cwd=REPO,
                         env=child_env(), capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and "not found" in res.stdout + res.stderr
    res = subprocess.run([sys.executable, "-m", "services.app.cli", "convert", str(tmp_path / "nothing"), str(tmp_path / "o.mcap")],
                         cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=60)
    assert res.returncode == 1 and "not found" in res.stderr


# ----------------------------------------------------------------------------- real-download quirks (issue 19)

def _copy(dataset, dst):
    import shutil

    shutil.copytree(dataset, dst)
    return dst


def test_rows_without_image_files_skip_their_frame_when_opened(tmp_path, dataset, caplog):
    """A data.csv row naming an image that is not there (real downloads have such cam1 rows): the pair is left
    out of frame_stamps_ns, counted, one warning per camera; the rest plays."""
    bad = _copy(dataset, tmp_path / "bad")
    gone = [T0 + 2 * 50_000_000, T0 + 7 * 50_000_000]
    for t in gone:
        (bad / "mav0" / "cam1" / "data" / f"{t}.png").unlink()
    with caplog.at_level("WARNING", logger="shared.euroc_reader"):
        ds = EurocDataset(bad)
    assert ds.stats["unreadable_images"] == 2 and len(ds.frame_stamps_ns) == N_FRAMES - 2
    assert not set(gone) & set(ds.frame_stamps_ns.tolist())
    warnings = [r.getMessage() for r in caplog.records if "do not exist" in r.getMessage()]
    assert len(warnings) == 1 and "cam1" in warnings[0] and "2 data.csv rows" in warnings[0], warnings
    frames = [m for m in ds.messages() if type(m).__name__ == "MultiCameraFrame"]
    assert [m.header.stamp_ns for m in frames] == ds.frame_stamps_ns.tolist()
    assert [m.header.seq for m in frames] == list(range(N_FRAMES - 2))
    assert ds.stats["unreadable_images"] == 2  # not counted a second time when played


def _long_imu_dataset(dataset, dst, before_s: float, after_s: float):
    """``dataset`` with its IMU extended to ``before_s`` before and ``after_s`` after the frames (200 Hz)."""
    d = _copy(dataset, dst)
    csv = d / "mav0" / "imu0" / "data.csv"
    head, *rows = csv.read_text().splitlines()
    first, last = int(rows[0].split(",")[0]), int(rows[-1].split(",")[0])
    pre = np.arange(first - int(before_s * 1e9), first, 5_000_000, dtype=np.int64)
    post = np.arange(last + 5_000_000, last + int(after_s * 1e9), 5_000_000, dtype=np.int64)
    fmt = lambda t: f"{t},0.001,-0.002,0.003,0.1,0.2,9.8"  # noqa: E731
    csv.write_text("\n".join([head, *map(fmt, pre), *rows, *map(fmt, post)]) + "\n")
    return d, len(pre), len(post)


def test_imu_outside_the_frames_span_is_not_played(tmp_path, dataset):
    long, n_pre, n_post = _long_imu_dataset(dataset, tmp_path / "long", before_s=20.0, after_s=60.0)
    ds = EurocDataset(long)
    everything = list(ds.messages())  # default: every sample (what convert needs)
    assert sum(type(m).__name__ == "ImuSample" for m in everything) == 110 + n_pre + n_post
    margin = 300_000_000
    msgs = list(ds.messages(imu_margin_ns=margin))
    imu = [m.header.stamp_ns for m in msgs if type(m).__name__ == "ImuSample"]
    t0, t1 = ds.frame_span_ns()
    assert (t0, t1) == (T0, T0 + 9 * 50_000_000)
    assert min(imu) >= t0 - margin and max(imu) <= t1 + margin
    assert min(imu) < t0 - margin + 5_000_000 and max(imu) > t1 + margin - 5_000_000  # the whole margin kept
    assert ds.stats["imu_outside_frames"] == 110 + n_pre + n_post - len(imu)
    assert sum(type(m).__name__ == "MultiCameraFrame" for m in msgs) == N_FRAMES
    stamps = [m.header.stamp_ns for m in msgs]
    assert stamps == sorted(stamps)


def test_realtime_player_does_not_play_a_minute_of_trailing_imu(tmp_path, dataset):
    """A trimmed folder whose IMU runs on 60 s past its 0.45 s of frames: played at sensor rate, the stream
    ends about player.imu_margin_s after the last frame, not a minute later."""
    long, _, _ = _long_imu_dataset(dataset, tmp_path / "long", before_s=30.0, after_s=60.0)
    with router() as tcfg:
        cfg = _config(tmp_path, tcfg, mode="rate", rate=1.0, imu_margin_s=0.5)
        with Node("tester", tcfg) as node:
            col = Collector(node)
            t_start = time.monotonic()
            proc, lines = _start_player(cfg, long)
            assert wait_for(lambda: col.ends, 20.0), "".join(lines)
            took = time.monotonic() - t_start
            _finish(proc, lines)
    print(f"realtime, 0.45 s of frames inside 90 s of IMU: stream ended after {took:.1f} s")
    assert len(col.frames) == N_FRAMES and col.ends[0].frames_sent == N_FRAMES
    assert len(col.imu) == 291  # every 5 ms from 0.5 s before the first frame to 0.5 s after the last, ends included
    assert "imu_outside_frames" in "".join(lines)


def test_run_finds_ground_truth_where_downloads_keep_it(tmp_path, dataset):
    from services.app.run_outputs import find_ground_truth

    d = _copy(dataset, tmp_path / "asl")
    asl = d / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    (d / "groundtruth_tum.txt").write_text("1403715523.912143104 0 0 0 0 0 0 1\n")
    assert find_ground_truth(d) == asl and find_ground_truth(d / "mav0") == asl  # the ASL file first
    asl.unlink()
    assert find_ground_truth(d) == d / "groundtruth_tum.txt" == find_ground_truth(d / "mav0")
    (d / "groundtruth_tum.txt").unlink()
    assert find_ground_truth(d) is None


def test_a_start_in_mid_flight_leaves_out_the_earlier_frames_and_imu(tmp_path, dataset):
    """player.start_s: the first frame played is the first at or after first + start; IMU from the margin before
    it (EuRoC folder) or from the start (a recording); the frames' seq counts from 0; past the end: a clear error."""
    ds = EurocDataset(dataset)
    start = 3 * 50_000_000 - 1  # just before the 4th frame
    msgs = list(ds.messages(imu_margin_ns=20_000_000, start_ns=start))
    frames = [m for m in msgs if isinstance(m, MultiCameraFrame)]
    imu = [m.header.stamp_ns for m in msgs if not isinstance(m, MultiCameraFrame)]
    assert [f.header.stamp_ns for f in frames] == ds.frame_stamps_ns[3:].tolist()
    assert [f.header.seq for f in frames] == list(range(N_FRAMES - 3))
    assert T0 + 150_000_000 - 20_000_000 <= min(imu) < T0 + 150_000_000 - 15_000_000
    whole = [m.header.stamp_ns for m in ds.messages(imu_margin_ns=20_000_000) if not isinstance(m, MultiCameraFrame)]
    assert imu == [t for t in whole if t >= min(imu)]  # nothing else left out
    with pytest.raises(DatasetError, match="no frame 10.0 s or more after the first"):
        list(ds.messages(start_ns=10_000_000_000))
    with pytest.raises(ValueError):
        list(ds.messages(start_ns=-1))
    mcap = tmp_path / "tiny.mcap"
    euroc_to_mcap(dataset, mcap)
    rec = list(open_source(mcap).messages(start_ns=start))
    first = min(m.header.stamp_ns for m in open_source(mcap).messages())
    assert min(m.header.stamp_ns for m in rec) >= first + start
    assert [m.header.stamp_ns for m in rec if isinstance(m, MultiCameraFrame)] == ds.frame_stamps_ns[3:].tolist()
