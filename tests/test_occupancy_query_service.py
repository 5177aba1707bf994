"""``map/query`` live: a real ``sigmaslam mapping`` process on loopback Zenoh maps the ray-cast room from estimator
states and depth frames, then answers point, segment and box questions through the client API
(services/app/occupancy_client.py) against the room's truth; bad questions get an error reply and the process goes
on; after SIGTERM the saved map answers the same questions offline with the same answers."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import yaml

from occupancy_room import BALL, BOX, K, SIGMA_M, H, W, observed_points, room_renderer, views
from services.app.occupancy_client import LiveOccupancy, QueryError, SavedOccupancy
from services.mapping.combined import FREE, OCCUPIED, UNKNOWN
from services.mapping.query_service import query_message
from shared import codec, topics
from shared import messages as m
from shared.codec import Header
from shared.config import to_dict
from tests.helpers_zenoh import REPO, child_env, router, wait_for, wait_for_heartbeat
from transport.pubsub import Publisher, Subscriber
from transport.session import open_session

MAX_POINTS = 50_000


def _state(stamp: int, T_WS: np.ndarray) -> m.EstimatorState:
    return m.EstimatorState(header=Header(stamp_ns=stamp, frame_id="W"), T_WS=T_WS, v_W=np.zeros(3),
                            gyro_bias=np.zeros(3), acc_bias=np.zeros(3), covariance=np.eye(15))


def _feed(session, ns: str, tcfg, integrated) -> int:
    renderer = room_renderer()
    p_state = Publisher(session, f"{ns}/{topics.STATE.key}", m.EstimatorState, tcfg, block=True)
    p_depth = Publisher(session, f"{ns}/{topics.DEPTH_FUSED.key}", m.DepthFrame, tcfg, block=True)
    assert p_depth.wait_for_subscribers(10.0) and p_state.wait_for_subscribers(10.0)
    poses = views(0) + views(1)
    for i, T_WC in enumerate(poses):
        stamp = (i + 1) * 100_000_000
        d = renderer.render(K, W, H, T_WC)
        p_state.publish(_state(stamp, T_WC))  # T_SC = identity: the body is the camera
        time.sleep(0.02)
        p_depth.publish(m.DepthFrame(header=Header(stamp_ns=stamp, frame_id="cam0"), depth=d,
                                     sigma=np.full_like(d, SIGMA_M), K=K, T_WC=np.eye(4), source="gt"))
        assert wait_for(lambda: integrated() >= i + 1, 20.0)
    return len(poses)


def _check_against_truth(occ, rng) -> None:
    renderer = room_renderer()
    for k in (0, 1):
        free, surface = observed_points(renderer, k, rng, 1000)
        got = occ.points(free)
        assert np.mean(got.state == FREE) > 0.99 and not (got.state == OCCUPIED).any()
        assert np.mean(occ.points(surface).state == FREE) < 0.02
    hidden = np.array([[6.5, 2.0, 1.0], [3.0, 2.5, -0.4], [*(BOX[0] + BOX[1]) / 2], [*BALL[0]]])
    assert (occ.points(hidden).state == UNKNOWN).all()
    seg = occ.segments(np.array([[2.5, 1.5, 1.4], [3.0, 2.9, 0.5]]), np.array([[7.0, 1.5, 1.4], [3.0, 3.6, 0.5]]),
                       np.array([0.0, 0.1]))
    assert seg.hit.tolist() == [True, False] and abs(seg.hit_distance_m[0] - 3.5) <= 0.03 and seg.free[1]
    box = occ.boxes(np.array([[2.8, 1.3, 1.2], [5.8, 1.0, 0.5]]), np.array([[3.1, 1.6, 1.5], [6.2, 1.3, 0.8]]))
    assert box.any_occupied.tolist() == [False, True] and box.unknown_fraction[0] == 0


def _bad_questions(session, occ: LiveOccupancy) -> None:
    with pytest.raises(QueryError, match="NaN"):
        occ.points(np.array([[1.0, np.nan, 0.0]]))
    with pytest.raises(QueryError, match="max_points"):
        occ.points(np.zeros((MAX_POINTS + 1, 3)))
    with pytest.raises(QueryError, match="lo <= hi"):
        occ.boxes(np.ones((1, 3)), np.zeros((1, 3)))
    odd = m.OccupancyQuery(header=Header(stamp_ns=0, frame_id="W"), kind="spheres", a_W=np.zeros((1, 3)))
    with pytest.raises(QueryError, match="spheres"):
        occ.ask(odd)
    with pytest.raises(QueryError, match="one radius or one per segment"):
        occ.ask(query_message("segments", np.zeros((3, 3)), np.ones((3, 3)), np.array([0.1, 0.2])))
    for payload in (b"not a message", codec.encode(m.Heartbeat(header=Header(stamp_ns=1), service="x", pid=1,
                                                                 state="running"))):
        replies = list(session.get(occ.key_expr, payload=payload, timeout=5.0))
        assert len(replies) == 1 and replies[0].ok is None
        assert replies[0].err.payload.to_bytes()  # the reason, as text


def test_map_query_live_then_offline(tmp_path):
    out = tmp_path / "run"
    with router() as tcfg:
        cfg = {"transport": to_dict(tcfg) | {"stats_period_s": 0.2, "heartbeat_period_s": 0.2},
               "mapping": {"depth_topic": "depth/fused", "pose_wait_s": 2.0, "output_dir": str(out),
                           "query": {"max_points": MAX_POINTS}}}
        cfg_path = tmp_path / "system.yaml"
        cfg_path.write_text(yaml.safe_dump(cfg))
        proc = subprocess.Popen([sys.executable, "-m", "services.app.cli", "mapping", str(cfg_path)], cwd=REPO,
                                env=child_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        lines: list[str] = []
        threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")), daemon=True).start()
        try:
            with open_session(tcfg) as session:
                assert wait_for_heartbeat(session, tcfg, "mapping", 60.0, proc), "".join(lines)
                stats: list[m.ServiceStats] = []
                Subscriber(session, f"{tcfg.namespace}/stats/mapping", m.ServiceStats, "all", 256,
                           handler=stats.append)

                def integrated() -> int:
                    s = stats[-1] if stats else None
                    return int(s.stage_count[list(s.stage_names).index("integrate")]) if s and "integrate" in \
                        s.stage_names else 0

                n = _feed(session, tcfg.namespace, tcfg, integrated)
                with LiveOccupancy(tcfg, timeout_s=10.0, session=session) as occ:
                    try:
                        _check_against_truth(occ, np.random.default_rng(5))
                    except QueryError as exc:
                        raise AssertionError("".join(lines)) from exc
                    _bad_questions(session, occ)
                    p = np.random.default_rng(6).uniform([0, 0, 0], [6, 5, 3], (MAX_POINTS, 3))
                    live = occ.points(p)
                    assert proc.poll() is None, "".join(lines)
                    assert (live.state == FREE).sum() > 1000 and (live.state == OCCUPIED).sum() > 100
                    s = stats[-1]
                    counters = dict(zip(s.counter_names, s.counter_values.tolist()))
                    assert wait_for(lambda: dict(zip(stats[-1].counter_names, stats[-1].counter_values.tolist()))
                                    .get("map/query_refused", 0) >= 7, 5.0), counters
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=60)
        finally:
            proc.kill()
    assert proc.returncode == 0, "".join(lines)
    saved = SavedOccupancy(out)
    assert sum(sm.n_frames for sm in saved.mapper.submaps) == n
    offline = saved.points(p)
    np.testing.assert_array_equal(offline.state, live.state)
    np.testing.assert_array_equal(offline.log_odds, live.log_odds)
    _check_against_truth(saved, np.random.default_rng(5))
