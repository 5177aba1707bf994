"""Stage timers (overruns, percentiles, rate) and the ServiceStats message built from them."""

import math

import numpy as np
import pytest

from shared import codec
from shared.messages import Heartbeat, ServiceStats
from transport.queues import BoundedQueue
from transport import stats as stats_module
from transport.stats import StageTimer, StatsCollector, heartbeat


def test_overruns_counted_against_budget():
    t = StageTimer("track", budget_ms=10.0)
    for ms in [1, 5, 9.9, 10.1, 50, 3]:
        t.record(ms / 1e3)
    s = t.snapshot()
    assert (s.count, s.overruns, s.budget_ms) == (6, 2, 10.0)
    assert s.p50_ms == pytest.approx(np.percentile([1, 5, 9.9, 10.1, 50, 3], 50))
    assert s.p99_ms == pytest.approx(np.percentile([1, 5, 9.9, 10.1, 50, 3], 99))


def test_context_manager_measures_time_and_rate(fake_clock):
    fake_clock.install(stats_module)
    t = StageTimer("work", budget_ms=5.0)
    for _ in range(5):
        with t:
            fake_clock.advance(0.010)  # the stage takes 10 ms
        fake_clock.advance(0.015)  # and starts every 25 ms
    s = t.snapshot()
    assert s.count == 5 and s.overruns == 5
    assert s.p50_ms == pytest.approx(10.0) and s.p99_ms == pytest.approx(10.0)
    assert s.rate_hz == pytest.approx(40.0)  # four intervals of 25 ms between the five items


def test_no_budget_never_overruns_and_window_expires(fake_clock):
    fake_clock.install(stats_module)
    t = StageTimer("free", window_s=0.05)
    t.record(10.0)
    assert t.snapshot().overruns == 0 and math.isnan(t.snapshot().budget_ms)
    fake_clock.advance(0.049)
    assert t.snapshot().p50_ms == pytest.approx(10e3)  # still in the window
    fake_clock.advance(0.002)
    s = t.snapshot()
    assert s.count == 1 and math.isnan(s.p50_ms) and s.rate_hz == 0.0
    with pytest.raises(ValueError, match="budget"):
        StageTimer("bad", budget_ms=0)


def test_collector_builds_service_stats_that_survive_the_wire():
    c = StatsCollector("frontend")
    a = c.add_stage(StageTimer("detect", 20.0))
    c.add_stage(StageTimer("track"))
    a.record(0.030)
    q = BoundedQueue("latest", 2)
    for i in range(5):
        q.put(i)
    c.add_queue("sensors/frame", q.counters)
    msg = codec.decode(codec.encode(c.collect(seq=3)), ServiceStats)
    assert msg.service == "frontend" and msg.header.seq == 3 and msg.uptime_s >= 0 and msg.rss_mb > 1
    assert msg.stage_names == ("detect", "track")
    assert list(msg.stage_count) == [1, 0] and list(msg.stage_overruns) == [1, 0]
    assert msg.stage_budget_ms[0] == 20.0 and math.isnan(msg.stage_budget_ms[1])
    assert msg.queue_names == ("sensors/frame",)
    assert (msg.queue_received[0], msg.queue_dropped[0], msg.queue_depth[0]) == (5, 3, 2)


def test_heartbeat_message():
    hb = heartbeat("backend", "starting", seq=2)
    assert isinstance(hb, Heartbeat) and hb.service == "backend" and hb.pid > 0 and hb.header.seq == 2
    with pytest.raises(ValueError, match="state"):
        heartbeat("backend", "sleeping")
