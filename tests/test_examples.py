"""The numbered scripts in examples/ run and say what they claim: each on small inputs (a 1.5 s replica, a
tiny saved map, a fake pose publisher on a loopback router), asserting on what its ``main`` returns and prints."""

from __future__ import annotations

import importlib.util
import threading
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
EXAMPLES = sorted((REPO / "examples").glob("[0-9][0-9]_*.py"))
SHORT_S = 1.5  # seconds of the short V1_02 replica (the one tests/test_mapping_replica.py renders too)


def load(stem: str):
    """Import examples/<stem>.py as a module (its name starts with a digit: loaded from its path)."""
    spec = importlib.util.spec_from_file_location(f"example_{stem}", REPO / "examples" / f"{stem}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def short_replica() -> Path:
    from services.app.synth.api import ensure_replica

    return ensure_replica("V1_02", "vicon-a", imu="real", duration_s=SHORT_S, progress=False)


def test_examples_are_numbered_narrated_and_parse_help(capsys):
    assert [p.name[:3] for p in EXAMPLES] == ["01_", "02_", "03_", "04_", "05_", "06_"], EXAMPLES
    for path in EXAMPLES:
        mod = load(path.stem)
        assert mod.__doc__ and mod.__doc__.startswith(path.name[:2] + ":"), path.name  # the story comes first
        assert "python -m examples." + path.stem in mod.__doc__, f"{path.name}: docstring shows no command line"
        with pytest.raises(SystemExit) as exc:
            mod.main(["--help"])
        assert exc.value.code == 0
    assert "usage:" in capsys.readouterr().out


def test_01_read_replica(short_replica, capsys):
    facts = load("01_read_replica").main(["--replica", str(short_replica)])
    out = capsys.readouterr().out
    assert facts["cameras"] == ["cam0", "cam1"]
    assert 29 <= facts["frames"] <= 31 and abs(facts["span_s"] - SHORT_S) < 0.1  # 20 Hz stereo
    assert abs(facts["imu_hz"] - 200) < 2 and facts["imu_between"][:5] == [10] * 5  # 10 IMU samples per frame
    assert abs(facts["acc_norm"] - 9.81) < 0.3  # V1_02 starts on the ground: the accelerometer reads gravity
    assert facts["gt_poses"] > 0 and facts["scene_mesh"] and facts["image_shape"] == (480, 752)
    assert "cam1: 752x480 px" in out and "m from cam0" in out and "ground truth:" in out


def test_04_load_saved_map(tmp_path, capsys):
    """A one-submap map of a wall 2 m in front of a camera moving sideways, saved as the mapping service saves it."""
    from services.mapping.io import save_map
    from services.mapping.submaps import SubmapMapper
    from shared.geometry import make_T

    w, h, sigma = 64, 48, 0.03
    K = np.array([[40.0, 0, w / 2 - 0.5], [0, 40.0, h / 2 - 0.5], [0, 0, 1]])
    mapper = SubmapMapper()
    for i in range(6):
        depth = np.full((h, w), 2.0, np.float32)
        mapper.integrate(depth, np.full_like(depth, sigma), K, make_T(np.eye(3), [0.1 * i, 0, 0]), np.eye(4),
                         i * 50_000_000)
    run = tmp_path / "run"
    save_map(mapper, run / "map" / "dense.npz")  # where a run's mapping writes it

    facts = load("04_load_saved_map").main([str(run)])
    out = capsys.readouterr().out
    assert len(facts["submaps"]) == 1 and "1 submaps, 2.5 cm voxels" in out
    sm = facts["submaps"][0]
    assert sm["frames"] == 6 and sm["vertices"] > 1000 and sm["p_WM"] == [0.0, 0.0, 0.0]
    assert sm["median_abs_L_at_vertices"] < 0.5  # the mesh is the L = 0 surface
    assert abs(sm["median_sigma_map_m"] - sigma) < 0.01  # eq. 7's map sigma gives back the depth sigma
    assert sm["free_in_front"] > 0.9 and sm["occupied_behind"] > 0.9
    mesh = Path(facts["mesh"])
    assert mesh == run / "mesh_from_map.ply" and mesh.read_bytes().startswith(b"ply\n")
    ext = facts["extent_m"]  # the wall seen from x = 0 .. 0.5 m: wide in x and y, flat in z
    assert facts["vertices"] == sm["vertices"] and ext[0] > 2.0 and ext[1] > 1.5 and ext[2] < 0.05

    other = tmp_path / "elsewhere.ply"
    facts2 = load("04_load_saved_map").main([str(run / "map" / "dense.npz"), "--out", str(other)])
    assert other.is_file() and facts2["faces"] == facts["faces"]


def test_05_query_occupancy(tmp_path, capsys):
    """The two-submap room saved as a run saves it, with a trajectory file: the example's answers match the room."""
    from occupancy_room import mapped_room
    from services.mapping.io import save_map
    from shared.euroc import PoseSeries, write_tum

    run = tmp_path / "run"
    save_map(mapped_room()[0], run / "map" / "dense.npz")
    p = np.array([[2.5, 1.5, 1.4], [3.0, 1.5, 1.4], [7.0, 1.5, 1.4]])  # the last through the far wall (x = 6)
    write_tum(run / "trajectory.txt", PoseSeries(np.arange(3) * 10**9, p, np.tile([1.0, 0, 0, 0], (3, 1))))
    facts = load("05_query_occupancy").main([str(run), "--radius", "0.05", "--extent", "0", "0", "0", "6", "5", "3"])
    out = capsys.readouterr().out
    assert facts["segment_hit"] and not facts["segment_free"] and abs(facts["hit_distance_m"] - 3.5) < 0.03, out
    assert facts["points"]["free"] > 0.3 and facts["points"]["occupied"] > 0.005 and "is refused" in out
    assert facts["box_any_occupied"] is False  # a 1 m box around (4.75, 1.5, 1.4): free space and unknown


def test_06_plan_on_grid(tmp_path, capsys):
    """The room's grid written as a run writes it, and a trajectory from in front of the box to beyond it."""
    from occupancy_room import mapped_room
    from services.mapping.grid import GridBuilder
    from services.mapping.grid_files import write_grid
    from shared.euroc import PoseSeries, write_tum

    run = tmp_path / "run"
    write_grid(GridBuilder().build(mapped_room()[0]), run)
    p = np.array([[3.3, 2.9, 1.0], [4.0, 2.0, 1.0], [5.4, 2.9, 1.0]])
    write_tum(run / "trajectory.txt", PoseSeries(np.arange(3) * 10**9, p, np.tile([1.0, 0, 0, 0], (3, 1))))
    facts = load("06_plan_on_grid").main([str(run), "--radius", "0.2"])
    out = capsys.readouterr().out
    assert facts["found"] and facts["straight_m"] < facts["length_m"] < 2 * facts["straight_m"], out
    assert "path of" in out and facts["clearance_m"] is None  # no replica given: no check against a mesh


def test_03_subscribe_to_poses(tmp_path, capsys):
    """A fake back end publishes states at 50 Hz (data time) on a loopback router; the example, given the run's
    config file, prints and counts them."""
    from helpers_zenoh import router
    from services.app.system_config import SystemConfig
    from shared import topics
    from shared.config import to_yaml
    from shared.messages import EstimatorState, Header
    from transport.pubsub import Publisher
    from transport.session import open_session

    with router() as tcfg:
        config = tmp_path / "config.yaml"
        config.write_text(to_yaml(SystemConfig(transport=tcfg)))
        stop = threading.Event()

        def publish() -> None:
            with open_session(tcfg) as session:
                pub = Publisher(session, topics.STATE.key_expr(tcfg.namespace), EstimatorState, tcfg)
                i = 0
                while not stop.wait(0.01):
                    T = np.eye(4)
                    T[0, 3] = 0.01 * i
                    header = Header(stamp_ns=1_000_000_000 + 20_000_000 * i, seq=i, frame_id="W")
                    pub.publish(EstimatorState(header=header, T_WS=T, v_W=np.array([0.5, 0, 0]), gyro_bias=np.zeros(3),
                                               acc_bias=np.zeros(3), covariance=np.eye(15) * 1e-4,
                                               status="initialising" if i % 10 == 0 else "tracking"))
                    i += 1
                pub.close()

        th = threading.Thread(target=publish, daemon=True)
        th.start()
        try:
            facts = load("03_subscribe_to_poses").main(["--config", str(config), "--count", "12", "--timeout", "30"])
        finally:
            stop.set()
            th.join(10)
    out = capsys.readouterr().out
    assert facts["poses"] == 12 and facts["dropped"] == 0, out
    assert facts["statuses"]["tracking"] == 12 and facts["statuses"].get("initialising", 0) <= 2  # skipped, counted
    x = np.array([p[0] for p in facts["positions"]])
    assert np.all(np.diff(x) > 0) and np.allclose(np.round(x / 0.01), x / 0.01)  # in order, values as published
    assert 40 <= facts["rate_hz"] <= 50.01  # 50 Hz in data time, less the skipped placeholders
    assert f"subscribing to {tcfg.namespace}/estimator/state" in out and "sigma_p=10.0 mm tracking" in out


@pytest.mark.e2e
def test_02_estimator_in_process(short_replica, tmp_path, capsys):
    facts = load("02_estimator_in_process").main(["--replica", str(short_replica), "--max-frames", "0",
                                                  "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert 29 <= facts["frames"] <= 31 and facts["poses"] >= facts["frames"] - 2
    assert facts["ate_rmse_m"] < 0.02, out  # standing on the ground: a few mm
    lines = (tmp_path / "trajectory_causal.txt").read_text().splitlines()
    assert len([ln for ln in lines if ln and not ln.startswith("#")]) == facts["poses"]
    assert "causal ATE (SE(3))" in out
