"""The pipeline bench on a small or busy computer (tools/bench_load.py, tools/bench_pipeline.py): core lists, pinning,
the competing busy processes, and the run's health line from known measurements."""

from __future__ import annotations

import os
import time

import psutil
import pytest

from tools.bench_load import BusyLoad, available_cpus, parse_cpus, pinned
from tools.bench_pipeline import format_health, run_health

linux_only = pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="core affinity is Linux's")


def test_parse_cpus_reads_taskset_lists_and_refuses_the_rest():
    first = min(available_cpus())
    assert parse_cpus(str(first)) == [first]
    cpus = sorted(available_cpus())
    assert parse_cpus(",".join(map(str, reversed(cpus)))) == cpus  # sorted, unique
    if len(cpus) >= 2 and cpus[1] == cpus[0] + 1:
        assert parse_cpus(f"{cpus[0]}-{cpus[1]},{cpus[0]}") == cpus[:2]
    for bad, word in (("", "expected core numbers"), ("a", "expected core numbers"), ("1-", "expected core numbers"),
                      ("3-1", "runs backwards"), ("4096", "not available here")):
        with pytest.raises(ValueError, match=word):
            parse_cpus(bad)


@linux_only
def test_pinned_restricts_this_thread_and_restores_it():
    before = os.sched_getaffinity(0)
    one = min(before)
    with pinned([one]):
        assert os.sched_getaffinity(0) == {one}
    assert os.sched_getaffinity(0) == before
    with pinned(None):  # no --cpus: unchanged
        assert os.sched_getaffinity(0) == before


@pytest.mark.service
@linux_only
def test_busy_load_spins_at_normal_priority_in_sessions_of_their_own_and_stops():
    one = [min(available_cpus())]
    with BusyLoad(2, one) as load:
        assert len(load.pids) == 2
        procs = [psutil.Process(pid) for pid in load.pids]
        time.sleep(0.5)
        for p in procs:
            assert os.getsid(p.pid) == p.pid != os.getsid(0)  # a separate program: its own session
            assert p.nice() == 0 and os.sched_getaffinity(p.pid) == set(one)
            assert p.cpu_times().user > 0.05  # it spins
    assert all(not p.is_running() or p.status() == psutil.STATUS_ZOMBIE for p in procs)
    with pytest.raises(ValueError, match="--load"):
        BusyLoad(-1)


def _res(**health):
    stages = {"mapping.integrate": {"n": 70}}
    latency = {"state": {"n": 500, "median": 20.0, "p99": 48.5}, "depth": {"n": 80, "rate_hz": 3.2},
               "state_sent": {"n": 500, "median": 19.0, "p99": 45.5},
               "state_sensor": {"n": 500, "median": 19.5, "p99": 61.0}}
    run_stats = {"frames_sent": 501, "frames_without_state": 0,
                 "services": {"mapping": {"counters": {"dropped_no_pose": 2, "dropped_waiting_full": 0,
                                                       "skipped_no_estimate": 3},
                                          "queues": {"depth/stereo": {"received": 80, "dropped": 1}}},
                              "backend": {"counters": {"keyframes_skipped": 4}}}}
    return {"stages": stages, "latency_ms": latency, "cpu_count": 2}, run_stats


def test_run_health_counts_what_the_machine_cost():
    res, run_stats = _res()
    h = run_health(res, run_stats, {"ate_rmse_m": 0.0123})
    assert h == {"frames_sent": 501, "frames_without_state": 0, "pose_latency_p50_ms": 20.0, "pose_latency_p99_ms": 48.5,
                 "pose_latency_sent_p50_ms": 19.0, "pose_latency_sent_p99_ms": 45.5,
                 "pose_latency_sensor_p50_ms": 19.5, "pose_latency_sensor_p99_ms": 61.0, "depth_frames": 80, "depth_rate_hz": 3.2, "mapping_integrated": 70,
                 "mapping_dropped": {"dropped_no_pose": 2, "queue depth/stereo": 1}, "keyframes_skipped": 4,
                 "causal_ate_m": 0.0123}
    res.update(health=h, machine={"cpus": [0], "load": 2, "loadavg_before": [1.0, 0.5, 0.25],
                                  "loadavg_after": [3.0, 1.5, 0.75]})
    line = format_health(res)
    assert line.startswith("on cores 0 with 2 busy process(es) (load average before 1.00 0.50 0.25, after 3.00")
    assert "0 of 501 frames without a state" in line and "p50 20.0 / p99 48.5 ms" in line and "(3.2 Hz)" in line
    assert "as sent 19.0 / 45.5; from the sensor clock 19.5 / 61.0" in line
    assert "causal ATE 0.0123 m" in line
    assert "causal ATE -" in format_health({**res, "health": run_health(res, run_stats, None)})


@pytest.mark.service
def test_bench_probe_logs_arrivals_from_a_process_of_its_own(zenoh_router, monkeypatch, tmp_path):
    """The bench's subscriber (tools/bench_probe.py) is a child process at the path to a pose's priority: the states
    published while it runs come back as arrivals per stamp, in a session and scheduling group of its own."""
    import numpy as np

    from helpers_zenoh import REPO, child_env, wait_for
    from services.app.scheduling import lowest_nice
    from shared import messages as m
    from shared import topics
    from tools.bench_probe import Probe
    from transport.node import Node

    monkeypatch.chdir(REPO)
    monkeypatch.setenv("PYTHONPATH", child_env()["PYTHONPATH"])
    cfg = zenoh_router
    sets = [f"transport.namespace={cfg.namespace}", f"transport.connect=[{cfg.connect[0]}]"]
    stamps = [1_000_000_000 + k * 50_000_000 for k in range(5)]
    t0 = time.time_ns()
    with Node("talker", cfg, handle_signals=False) as node, Probe(None, sets, tmp_path / "arrivals.npz") as probe:
        assert os.getsid(probe.proc.pid) == probe.proc.pid
        assert psutil.Process(probe.proc.pid).nice() == max(-10, lowest_nice())
        pub = node.publisher(topics.STATE)
        assert pub.wait_for_subscribers(10.0)
        for s in stamps:
            pub.publish(m.EstimatorState(header=m.Header(stamp_ns=s), T_WS=np.eye(4), v_W=np.zeros(3),
                                     gyro_bias=np.zeros(3), acc_bias=np.zeros(3), covariance=np.eye(15)))
            time.sleep(0.02)
        time.sleep(0.5)
    got, arrivals = probe.log.get("state")
    assert got.tolist() == stamps and np.all(arrivals >= t0) and np.all(np.diff(arrivals) >= 0)
    sent_stamps, sent = probe.log.get_sent("state")  # the talker's put times come back with them
    assert sent_stamps.tolist() == stamps and np.all(sent >= t0 - 1_000_000) and np.all(sent <= arrivals + 1_000_000)
    assert probe.log.get("frame")[0].size == 0 and probe.proc.returncode == 0
    assert wait_for(lambda: not psutil.pid_exists(probe.proc.pid) or
                    psutil.Process(probe.proc.pid).status() == psutil.STATUS_ZOMBIE, 5.0)
