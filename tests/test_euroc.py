import numpy as np
import pytest

from shared.euroc import (PoseSeries, TrajectoryFileError, read_euroc_csv, read_trajectory, read_tum,
                          write_euroc_csv, write_tum)
from shared.paths import euroc_dir

DATA = euroc_dir()  # the shared EuRoC folder, else the files bundled in data/euroc


def _series(n=10):
    rng = np.random.default_rng(0)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return PoseSeries(np.arange(n, dtype=np.int64) * 5_000_000 + 1_403_715_000_000_000_000,
                      rng.normal(size=(n, 3)), q)


def test_real_groundtruth():
    gt = read_euroc_csv(DATA / "groundtruth" / "V1_02_medium.state_groundtruth_estimate0.csv.xz")
    assert len(gt) > 10000 and gt.v_WS is not None
    dt = np.diff(gt.stamps_ns)
    assert abs(np.median(dt) - 5_000_000) < 1000  # 200 Hz
    np.testing.assert_allclose(np.linalg.norm(gt.q_WS_wxyz, axis=1), 1.0)


@pytest.mark.parametrize("fmt", ["tum", "csv"])
def test_roundtrip(tmp_path, fmt):
    s = _series()
    p = tmp_path / ("x.txt" if fmt == "tum" else "x.csv")
    (write_tum if fmt == "tum" else write_euroc_csv)(p, s)
    r = read_trajectory(p)
    np.testing.assert_array_equal(r.stamps_ns, s.stamps_ns)
    np.testing.assert_allclose(r.p_WS, s.p_WS, atol=1e-8)
    np.testing.assert_allclose(r.q_WS_wxyz, s.q_WS_wxyz, atol=1e-8)


def test_errors(tmp_path):
    with pytest.raises(TrajectoryFileError, match="not found"):
        read_tum(tmp_path / "nope.txt")
    bad = tmp_path / "bad.csv"
    bad.write_text("1,2,3\n")
    with pytest.raises(TrajectoryFileError, match="columns"):
        read_euroc_csv(bad)
    s = _series()
    p = tmp_path / "back.csv"
    write_euroc_csv(p, s)
    lines = p.read_text().splitlines()
    lines[4], lines[5] = lines[5], lines[4]
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(TrajectoryFileError, match="row 4"):
        read_euroc_csv(p)


from shared.euroc_reader import DatasetError, EurocDataset  # noqa: E402
from services.app.datasets.euroc_writer import write_euroc  # noqa: E402
from shared.messages import ImuSample, MultiCameraFrame  # noqa: E402

CAM = {"T_BS": {"rows": 4, "cols": 4, "data": np.eye(4).ravel().tolist()}, "intrinsics": [450.0, 450.0, 16.0, 12.0],
       "resolution": [32, 24], "rate_hz": 20}
IMU = {"rate_hz": 200}


def _write(tmp_path, ncam, nframes=4):
    rng = np.random.default_rng(ncam)
    stamps = 10**9 + np.arange(nframes, dtype=np.int64) * 50_000_000
    frames = [(t, [rng.integers(0, 256, (24, 32), dtype=np.uint8) for _ in range(ncam)]) for t in stamps]
    ti = 10**9 + np.arange(40, dtype=np.int64) * 5_000_000
    imu = np.column_stack([ti, rng.normal(size=(40, 6))])
    write_euroc(tmp_path, {f"cam{i}": CAM for i in range(ncam)}, iter(frames), imu, IMU, _series())
    return frames, imu


@pytest.mark.parametrize("ncam", [2, 3])
def test_dataset_roundtrip(tmp_path, ncam):
    frames, imu = _write(tmp_path, ncam)
    ds = EurocDataset(tmp_path)
    msgs = list(ds.messages())
    got_f = [m for m in msgs if isinstance(m, MultiCameraFrame)]
    got_i = [m for m in msgs if isinstance(m, ImuSample)]
    assert len(got_f) == len(frames) and len(got_i) == len(imu)
    for (t, imgs), m in zip(frames, got_f):
        assert m.header.stamp_ns == t
        for a, b in zip(imgs, m.images):
            np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal([m.acc_S for m in got_i], imu[:, 4:])
    stamps = [m.header.stamp_ns for m in msgs]
    assert stamps == sorted(stamps)
    assert len(read_euroc_csv(ds.groundtruth_path)) == 10


def test_dataset_error_paths(tmp_path):
    frames, _ = _write(tmp_path, 2)
    root = tmp_path / "mav0"
    (root / "cam0" / "data" / f"{frames[1][0]}.png").write_bytes(b"not a png")
    (root / "cam1" / "data" / f"{frames[2][0]}.png").unlink()
    with open(root / "imu0" / "data.csv", "a") as f:
        f.write("1000000000,0,0,0,0,0,0\n")  # backwards
    ds = EurocDataset(tmp_path)
    n = sum(isinstance(m, MultiCameraFrame) for m in ds.messages())
    assert n == 2 and ds.stats["unreadable_images"] == 2 and ds.stats["backwards_stamps"] == 1
    (root / "cam1" / "sensor.yaml").write_text("%YAML:1.0\nrate_hz: 20\n")
    with pytest.raises(DatasetError, match="missing key 'T_BS'"):
        EurocDataset(tmp_path)
    with pytest.raises(DatasetError, match="not found"):
        EurocDataset(tmp_path / "nowhere")


def test_reader_accepts_real_sensor_yaml(tmp_path):
    _write(tmp_path, 2)
    root = tmp_path / "mav0"
    for c in ("cam0", "cam1"):
        (root / c / "sensor.yaml").write_text((DATA / "calib" / f"{c}_sensor.yaml").read_text())
    (root / "imu0" / "sensor.yaml").write_text((DATA / "calib" / "imu0_sensor.yaml").read_text())
    ds = EurocDataset(root)
    assert ds.camera_yaml["cam0"]["resolution"] == [752, 480] and ds.imu_yaml["rate_hz"] == 200


SEQUENCES = ("MH_01", "MH_02", "MH_03", "MH_04", "V1_01", "V1_02", "V2_01", "V2_03")


@pytest.mark.parametrize("seq", SEQUENCES)
def test_every_known_sequence_reads(seq):
    """The eight EuRoC sequences of the shared folder: ground truth (CSV or TUM, xz) and, where recorded, the IMU."""
    from services.app.synth.imu_sim import read_imu_csv
    from tests.helpers_data import require_sequence
    from shared.paths import has_real_imu

    files = require_sequence(seq)
    gt = read_trajectory(files["groundtruth"])
    assert len(gt) > 1000 and np.all(np.diff(gt.stamps_ns) > 0)
    stamps = np.loadtxt(files["image_timestamps"], dtype=np.int64)
    assert gt.stamps_ns[0] < stamps[len(stamps) // 2] < gt.stamps_ns[-1]
    assert has_real_imu(seq) == (seq not in ("MH_01", "MH_02"))
    if has_real_imu(seq):
        imu = read_imu_csv(files["imu"])
        assert abs(np.median(np.diff(imu.stamps_ns)) - 5_000_000) < 100_000


def test_replica_without_recorded_imu_says_so():
    from services.app.synth.replica import ReplicaSpec, resolve_files
    from tests.helpers_data import require_sequence

    require_sequence("MH_01")
    with pytest.raises(ValueError, match="no recorded IMU.*imu='sim'"):
        resolve_files(ReplicaSpec(sequence="MH_01", imu="real"))
    assert "imu" not in resolve_files(ReplicaSpec(sequence="MH_01", imu="sim"))


def test_euroc_groundtruth_keeps_velocity_and_biases(tmp_path):
    """17 columns: velocity and biases are read too (replica biases, tools/eval/diagnose.py); 8 columns: None."""
    rows = [[10**18 + k * 5_000_000, k, 0, 0, 1, 0, 0, 0, 0.5, 0, 0, 0.01, 0.02, 0.03, 0.1, 0.2, 0.3] for k in range(3)]
    (tmp_path / "gt.csv").write_text("\n".join(",".join(str(x) for x in r) for r in rows) + "\n")
    gt = read_euroc_csv(tmp_path / "gt.csv")
    np.testing.assert_allclose(gt.v_WS[:, 0], 0.5)
    np.testing.assert_allclose(gt.gyro_bias[1], [0.01, 0.02, 0.03])
    np.testing.assert_allclose(gt.acc_bias[2], [0.1, 0.2, 0.3])
    (tmp_path / "p.csv").write_text("\n".join(",".join(str(x) for x in r[:8]) for r in rows) + "\n")
    assert read_euroc_csv(tmp_path / "p.csv").gyro_bias is None
