"""No data lost, bad files and bad config: map saves killed mid-write, fuzzed EuRoC folders, bad config values.

(Recordings closed by SIGTERM / cut by SIGKILL are covered by tests/test_recorder.py; message decoders are
fuzzed in tests/test_codec.py.)
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from helpers_zenoh import REPO, child_env
from services.mapping.io import load_map
from services.app.system_config import load_system_config
from shared.config import ConfigError
from shared.euroc_reader import DatasetError, EurocDataset
from shared.messages import ImuSample, MultiCameraFrame

FULL = os.environ.get("SIGMASLAM_E2E", "") == "full"

SAVER = r"""
import sys, numpy as np
from services.mapping.config import SensorModelConfig, SubmapConfig
from services.mapping.io import save_map
from services.mapping.submaps import SubmapMapper
m = SubmapMapper(SensorModelConfig(voxel_size_m=0.05), SubmapConfig())
K = np.array([[200.0, 0, 80], [0, 200.0, 60], [0, 0, 1]])
depth = np.full((120, 160), 2.0, np.float32); depth[:, 80:] = 3.0
m.integrate(depth, np.full_like(depth, 0.05), K, np.eye(4), np.eye(4), 1)
i = 0
while True:
    T = np.eye(4); T[0, 3] = 0.01 * (i % 7)
    m.integrate(depth, np.full_like(depth, 0.05), K, T, np.eye(4), 2 + i)
    save_map(m, sys.argv[1]); i += 1
    print("saved", i, flush=True)
"""


def test_map_save_killed_mid_write_leaves_the_previous_complete_map(tmp_path):
    """SIGKILL at random moments of a save loop: map.npz always loads (old or new version, never half)."""
    path = tmp_path / "map.npz"
    rng = np.random.default_rng(4)
    mid_write = 0
    tries = 8 if FULL else 3
    for _ in range(tries):
        before = set(tmp_path.glob(".map.npz.*.tmp"))  # left by earlier kills
        proc = subprocess.Popen([sys.executable, "-c", SAVER, str(path)], cwd=REPO, env=child_env(),
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            line = proc.stdout.readline()  # the first save is complete
            assert line.startswith("saved"), proc.stderr.read()
            time.sleep(float(rng.uniform(0.0, 0.3)))
            # then kill as soon as a new file is being written (or after 3 s, wherever the saver is)
            deadline = time.monotonic() + 3.0
            while not set(tmp_path.glob(".map.npz.*.tmp")) - before and time.monotonic() < deadline:
                time.sleep(0.001)
            os.kill(proc.pid, signal.SIGKILL)
        finally:
            proc.wait(timeout=30)
        # a temporary file left behind means the kill landed before the rename: mid-write
        mid_write += bool(set(tmp_path.glob(".map.npz.*.tmp")) - before)
        mapper = load_map(path)
        assert len(mapper.submaps) >= 1 and mapper.submaps[0].store.n_blocks > 0
    # the kills landed at least once while a new file was being written (else the test proved nothing)
    assert mid_write >= 1 or tries < 3, mid_write
    # the mapping service removes the killed writers' temporary files at start, keeping the map
    from shared.map_folder import remove_stale_temps

    stale = list(tmp_path.glob(".map.npz.*.tmp"))
    assert sorted(remove_stale_temps(tmp_path)) == sorted(stale)
    assert not list(tmp_path.glob(".*.tmp")) and path.exists()


# ----------------------------------------------------------------------------- EuRoC folders, fuzzed

def _dataset(root, n_frames=3):
    """A minimal two-camera EuRoC ASL folder with valid sensor.yaml files."""
    mav = root / "mav0"
    cam_yaml = ("%YAML:1.0\nsensor_type: camera\nrate_hz: 20\nresolution: [16, 12]\ncamera_model: pinhole\n"
                "intrinsics: [10.0, 10.0, 8.0, 6.0]\ndistortion_model: radial-tangential\n"
                "distortion_coefficients: [0.0, 0.0, 0.0, 0.0]\n"
                "T_BS:\n  cols: 4\n  rows: 4\n  data: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]\n")
    for cam in ("cam0", "cam1"):
        (mav / cam / "data").mkdir(parents=True)
        (mav / cam / "sensor.yaml").write_text(cam_yaml)
        rows = ["#timestamp [ns],filename"]
        for k in range(n_frames):
            t = 1_000_000_000 + k * 50_000_000
            cv2.imwrite(str(mav / cam / "data" / f"{t}.png"), np.full((12, 16), 40 * k, np.uint8))
            rows.append(f"{t},{t}.png")
        (mav / cam / "data.csv").write_text("\n".join(rows) + "\n")
    (mav / "imu0").mkdir()
    (mav / "imu0" / "sensor.yaml").write_text("%YAML:1.0\nrate_hz: 200\n")
    rows = ["#timestamp [ns],w_x,w_y,w_z,a_x,a_y,a_z"]
    rows += [f"{1_000_000_000 + k * 5_000_000},0.1,0.0,0.0,0.0,0.0,9.81" for k in range(30)]
    (mav / "imu0" / "data.csv").write_text("\n".join(rows) + "\n")
    return mav


FILES = ("cam0/data.csv", "cam1/data.csv", "imu0/data.csv", "cam0/sensor.yaml", "imu0/sensor.yaml",
         "cam0/data/1000000000.png", "cam1/data/1050000000.png")
LINES = st.sampled_from(["", "x", "1,2", "nan,nan,nan,nan,nan,nan,nan", "1000000000,1.png", "-5,a.png",
                         "99999999999999999999999,0,0,0,0,0,0", "1050000000,0,0,0,inf,0,0", "1000000000,0,0,0,0,0,0",
                         "1000000000,1000000000.png", "1100000000,1100000000.png", ": : :", "[unclosed", "rate_hz: x"])


@st.composite
def _mutation(draw):
    target = draw(st.sampled_from(FILES))
    kind = draw(st.sampled_from(["truncate", "bytes", "lines", "delete"]))
    return target, kind, draw(st.integers(0, 400)), draw(st.binary(max_size=64)), draw(st.lists(LINES, max_size=4))


def _apply(mav, mutation):
    target, kind, cut, blob, lines = mutation
    f = mav / target
    data = f.read_bytes()
    if kind == "truncate":
        f.write_bytes(data[: cut % (len(data) + 1)])
    elif kind == "bytes":
        at = cut % (len(data) + 1)
        f.write_bytes(data[:at] + blob + data[at + len(blob):])
    elif kind == "lines":
        f.write_bytes(data + ("\n".join(lines) + "\n").encode())
    else:
        f.unlink()


@settings(max_examples=120 if FULL else 30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(_mutation(), min_size=1, max_size=3))
def test_fuzzed_euroc_folder_gives_dataset_error_or_clean_messages(tmp_path_factory, mutations):
    """Damaged files give a DatasetError naming the file, or clean messages; what was not damaged is not lost, and
    every frame the reader lists comes out or is counted as unreadable."""
    mav = _dataset(tmp_path_factory.mktemp("ds"))
    pristine = EurocDataset(mav.parent)
    want_imu = [(m.header.stamp_ns, m.omega_S.tolist(), m.acc_S.tolist()) for m in pristine.messages()
                if isinstance(m, ImuSample)]
    want_frames = {int(t): pristine.load_frame(t) for t in pristine.frame_stamps_ns}
    touched = set()
    for m in mutations:
        if (mav / m[0]).exists():
            _apply(mav, m)
            touched.add(m[0])
    try:
        ds = EurocDataset(mav.parent)
    except DatasetError as exc:
        assert str(exc)  # names the file
        return
    unreadable_at_open = ds.stats["unreadable_images"]
    imu, frames = [], {}
    last_imu = last_frame = -1
    for msg in ds.messages():
        t = msg.header.stamp_ns
        if isinstance(msg, ImuSample):
            assert t > last_imu and np.isfinite(msg.omega_S).all() and np.isfinite(msg.acc_S).all()
            imu.append((t, msg.omega_S.tolist(), msg.acc_S.tolist()))
            last_imu = t
        else:
            assert isinstance(msg, MultiCameraFrame) and t > last_frame
            assert all(img.dtype == np.uint8 and img.ndim == 2 for img in msg.images)
            frames[t] = msg.images
            last_frame = t
    # every listed frame came out, or failed to load and was counted
    assert len(frames) + ds.stats["unreadable_images"] - unreadable_at_open == len(ds.frame_stamps_ns), ds.stats
    assert len(imu) == len(ds.imu_stamps_ns)
    # nothing undamaged is lost: an untouched IMU file plays in full, an untouched frame comes out as it was
    if "imu0/data.csv" not in touched:
        assert imu == want_imu
    if not touched & {"cam0/data.csv", "cam1/data.csv"}:
        for t, images in want_frames.items():
            if not touched & {f"cam0/data/{t}.png", f"cam1/data/{t}.png"}:
                assert t in frames, (t, sorted(frames), ds.stats)
                assert all(np.array_equal(a, b) for a, b in zip(frames[t], images))


def test_missing_frames_imu_gaps_and_backwards_stamps_are_counted(tmp_path):
    mav = _dataset(tmp_path, n_frames=5)
    (mav / "cam1" / "data" / "1100000000.png").unlink()  # a missing image: frame skipped
    with open(mav / "imu0" / "data.csv", "a") as f:
        f.write("1000000000,0,0,0,0,0,0\n")  # backwards
        f.write("1145000000,0,0,0,0,0,0\n")  # duplicate of the last one
        f.write("1400000000,nan,0,0,0,0,9.8\n")  # NaN: skipped
        f.write("1600000000,0,0,0,0,0,9.8\n")  # after a 455 ms gap: kept (the estimator reports the gap)
    ds = EurocDataset(tmp_path)
    msgs = list(ds.messages())
    frames = [m for m in msgs if isinstance(m, MultiCameraFrame)]
    assert len(frames) == 4 and ds.stats["unreadable_images"] == 1
    assert ds.stats["backwards_stamps"] == 2 and ds.stats["nonfinite_imu"] == 1
    assert ds.imu_stamps_ns[-1] == 1_600_000_000


# ----------------------------------------------------------------------------- config values

@pytest.mark.parametrize("override, fragment", [
    ("depth.bogus=1", "unknown key"),
    ("depth.rate_hz=fast", "expected a number"),
    ("depth.rate_hz=-10", "rate_hz must be positive"),
    ("depth.inject_delay_ms=-1", "inject_delay_ms"),
    ("player.rate=-2", "player.rate"),
    ("player.mode=warp", "player.mode"),
    ("transport.stats_period_s=0", "stats_period_s"),
    ("transport.mode=server", "transport.mode"),
    ("frontend.affine_window_px=3", "affine_window_px"),
    ("frontend.affine_max_scale_change=0.9", "affine_max_scale_change"),
    ("backend=[1]", "expected a mapping"),
])
def test_bad_config_values_are_clear_errors(override, fragment):
    with pytest.raises(ConfigError, match=fragment):
        load_system_config(None, [override])


def test_a_service_given_a_bad_config_exits_2_with_the_key_named(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("mapping:\n  checkpoint_period_s: soon\n")
    proc = subprocess.run([sys.executable, "-m", "services.app.cli", "mapping", str(bad)], cwd=REPO, env=child_env(),
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert "mapping.checkpoint_period_s" in proc.stderr and "expected a number" in proc.stderr


def test_a_restarted_recorder_never_overwrites_the_cut_recording(tmp_path):
    from services.recorder.recording import fresh_path

    out = tmp_path / "run.mcap"
    assert fresh_path(out) == out
    out.write_bytes(b"cut by SIGKILL")
    assert fresh_path(out) == tmp_path / "run.1.mcap"
    (tmp_path / "run.1.mcap").write_bytes(b"")
    assert fresh_path(out) == tmp_path / "run.2.mcap"
    assert out.read_bytes() == b"cut by SIGKILL"
